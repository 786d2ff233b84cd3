"""Every script with `--env walker`, run as a process of its own for a tiny run (CleanRL's way of testing a
script), through the final held-out evaluation on the six courses (one episode each); and a bad
course parameter or name as one clear error."""

from __future__ import annotations

import csv
import json
import os

import numpy as np
import pytest
import script_runs

from envs.walker import WalkerEnv
from envs.walker.terrain import WalkerLevels

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
COURSES = {"BipedalWalker-v3", "BipedalWalkerHardcore-v3", "Stairs", "PitGap", "Stump", "Roughness"}
TINY = ["--env", "walker", "--num-envs", "2", "--num-steps", "16", "--num-minibatches", "4", "--update-epochs", "1",
        "--eval-episodes", "1", "--log-interval", "1"]
SCRIPTS = {
    "plr": ("plr.py", ["--level-buffer-size", "2", "--total-timesteps", "96"], "Robust PLR on walker"),
    "accel": ("accel.py", ["--level-buffer-size", "2", "--total-timesteps", "128"], "ACCEL on walker"),
    "paired": ("paired.py", ["--total-timesteps", "32"], "PAIRED on walker"),
    "paired_hient": ("paired_hient.py", ["--total-timesteps", "32"], "PAIRED+HiEnt on walker"),
    "paired_bc": ("paired_bc.py", ["--bidirectional", "--bc-interval", "1", "--total-timesteps", "32"], "PAIRED+BiBC on walker"),
    "paired_evo": ("paired_evo.py", ["--level-buffer-size", "2", "--total-timesteps", "128", "--bc-coef", "0.1",
                                     "--bc-interval", "1", "--bidirectional"], "PAIRED+Evo+BiBC on walker"),
}


def run(script, args, cwd):
    return script_runs.run([os.path.join(ROOT, script), *args], cwd, ENV, timeout=900)


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_script_runs_on_walker_and_evaluates_on_the_courses(name, tmp_path):
    script, flags, banner = SCRIPTS[name]
    result = run(script, [*TINY, *flags], tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert banner in result.stdout and "steps/s" in result.stdout
    (run_dir,) = [os.path.join(tmp_path, "runs", d) for d in os.listdir(tmp_path / "runs")]
    with open(os.path.join(run_dir, "eval.json")) as f:
        results = json.load(f)
    assert set(results) == COURSES | {"mean"}
    for course in COURSES:  # an untrained walker: no course solved (return > 230), a return on the env's scale
        assert results[course]["solved_rate"] == 0.0
        assert -250 < results[course]["mean_return"] < 230
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and {"roughness", "stair_steps", "difficulty"} <= set(rows[0])
    assert os.path.isfile(os.path.join(run_dir, "curves.png"))


def test_accel_walker_defaults_are_the_papers(tmp_path):
    """ACCEL's walker settings (Appendix A): easy generator, replay 0.9, buffer 1000, T 0.1, staleness 0.5,
    3 edits; PPO 16 x 2000, 5 epochs, 32 minibatches, lr 3e-4, gamma 0.99, lambda 0.9, entropy 1e-3."""
    import accel

    args = accel.resolve_args(accel.paper_args(env="walker"))
    assert (args.generator, args.replay_prob, args.level_buffer_size, args.temperature, args.staleness_coef,
            args.num_edits) == ("easy", 0.9, 1000, 0.1, 0.5, 3)
    assert (args.num_envs, args.num_steps, args.update_epochs, args.num_minibatches, args.learning_rate, args.gamma,
            args.gae_lambda, args.ent_coef, args.value_loss, args.normalize_returns) == (16, 2000, 5, 32, 3e-4, 0.99, 0.9, 1e-3, "huber", True)


def test_parameters_outside_their_ranges_are_refused():
    env = WalkerEnv(1, 0)
    levels = env.random_levels(1, np.random.default_rng(0))
    bad = WalkerLevels(levels.params.copy(), levels.seed.copy(), levels.course.copy())
    bad.params[0, 0] = 11.0  # roughness beyond its full range [0, 10]
    with pytest.raises(ValueError, match="roughness"):
        env.reset(bad)
    with pytest.raises(ValueError, match="Nowhere"):
        env.test_levels()["Nowhere"]
    env.close()


def test_unknown_generator_is_one_error_line(tmp_path):
    result = run("accel.py", [*TINY, "--generator", "empty"], tmp_path)
    assert result.returncode == 2 and result.stderr.startswith("error:") and "easy" in result.stderr
    assert not (tmp_path / "runs").exists()
