"""Adding an env is one module and one registry entry: the toy env of tests/toy_env.py, registered and
nothing else, trains for 2 updates under each of the six scripts, and `python -m envs.evaluate` evaluates
each run from its directory alone."""

from __future__ import annotations

import concurrent.futures
import json
import os
import subprocess

import pytest
import script_runs

TESTS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(TESTS)
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([TESTS, ROOT]), "OMP_NUM_THREADS": "1"}
# What a user's launcher would do after adding the entry to envs/__init__.py's REGISTRY itself.
REGISTERED = "import sys, runpy, toy_env; toy_env.register(); "
COMMON = ["--env", "toy", "--num-envs", "4", "--num-steps", "16", "--eval-episodes", "2", "--eval-interval", "1",
          "--checkpoint-interval", "1", "--levels-interval", "1", "--log-interval", "1", "--no-cuda"]
RUNS = {  # script: its options for 2 updates of 4 x 16 steps
    "plr.py": ["--total-timesteps", "128", "--level-buffer-size", "8"],
    "accel.py": ["--gradient-updates", "2", "--level-buffer-size", "8"],
    "paired.py": ["--total-timesteps", "128"],
    "paired_hient.py": ["--total-timesteps", "128"],
    "paired_bc.py": ["--total-timesteps", "128", "--bc-interval", "1"],
    "paired_evo.py": ["--total-timesteps", "128", "--level-buffer-size", "8"],
}


def run_registered(code: str, cwd) -> subprocess.CompletedProcess:
    return script_runs.run(["-c", REGISTERED + code], cwd, ENV)


def train_and_evaluate(script: str, cwd) -> tuple[subprocess.CompletedProcess, subprocess.CompletedProcess | None, str | None]:
    argv = [os.path.join(ROOT, script), *COMMON, *RUNS[script]]
    trained = run_registered(f"sys.argv = {argv!r}; runpy.run_path(sys.argv[0], run_name='__main__')", cwd)
    if trained.returncode != 0:
        return trained, None, None
    (name,) = os.listdir(os.path.join(cwd, "runs"))
    run_dir = os.path.join(cwd, "runs", name)
    evaluated = run_registered(f"from envs.evaluate import main; main([{run_dir!r}, '--no-capture-video'])", cwd)
    return trained, evaluated, run_dir


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    cwds = {script: tmp_path_factory.mktemp(script[:-3]) for script in RUNS}
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        futures = {script: pool.submit(train_and_evaluate, script, cwd) for script, cwd in cwds.items()}
        return {script: future.result() for script, future in futures.items()}


@pytest.mark.parametrize("script", list(RUNS))
def test_a_registered_toy_env_trains_and_evaluates_under_every_script(finished, script):
    trained, evaluated, run_dir = finished[script]
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert " on toy: " in trained.stdout
    with open(os.path.join(run_dir, "args.json")) as f:
        saved = json.load(f)
    assert saved["env"] == "toy" and saved["student"] == "toy_env:ToyStudent"
    with open(os.path.join(run_dir, "metrics.csv")) as f:
        assert len(f.read().splitlines()) >= 3  # a header and a row per update
    with open(os.path.join(run_dir, "eval.json")) as f:
        assert set(json.load(f)) == {"Near", "Far", "mean"}
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    with open(os.path.join(run_dir, "evaluation", "eval.json")) as f:
        assert set(json.load(f)) == {"Near", "Far", "mean"}


def test_the_toy_env_is_offered_by_help_and_an_unknown_env_is_one_error_line(tmp_path):
    shown = run_registered(f"sys.argv = ['plr.py', '--env', 'toy', '--help']; runpy.run_path({os.path.join(ROOT, 'plr.py')!r}, "
                           "run_name='__main__')", tmp_path)
    assert shown.returncode == 0 and "{maze,maze25,carracing,walker,toy}" in shown.stdout
    unknown = run_registered(f"sys.argv = ['plr.py', '--env', 'toys']; runpy.run_path({os.path.join(ROOT, 'plr.py')!r}, "
                             "run_name='__main__')", tmp_path)
    assert unknown.returncode == 2 and unknown.stderr.startswith("error: ") and len(unknown.stderr.splitlines()) == 1
    assert "toys" in unknown.stderr and os.listdir(tmp_path) == []
