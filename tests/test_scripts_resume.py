"""plr.py killed and resumed on CarRacing and on the walker must end exactly where an uninterrupted run
ends: the same metrics (timing aside) and the same held-out evaluation. Their state beyond the maze's
(return normalization, CarRacing's tracks, the walker's terrain) must survive the checkpoint too.

The four runs (two per env) are independent: a module fixture plays them two at a time."""

from __future__ import annotations

import concurrent.futures
import json
import os
import re

import pytest
from conftest import f1_track_file
from test_scripts_accel_evo import kill_and_resume, only_run_dir, read_metrics, run

# The tiniest runs of each env: 12 updates, a checkpoint after each, validation after updates 6 and 12;
# CarRacing is evaluated on the vanilla track and one F1 track.
CONFIGS = {
    "carracing": ["--env", "carracing", "--num-envs", "2", "--num-steps", "8", "--num-minibatches", "2", "--update-epochs", "1",
                  "--level-buffer-size", "2", "--total-timesteps", "192", "--eval-episodes", "1", "--eval-interval", "6",
                  "--checkpoint-interval", "1", "--log-interval", "1"],
    "walker": ["--env", "walker", "--num-envs", "2", "--num-steps", "16", "--num-minibatches", "4", "--update-epochs", "1",
               "--level-buffer-size", "2", "--total-timesteps", "384", "--eval-episodes", "1", "--eval-interval", "6",
               "--checkpoint-interval", "1", "--log-interval", "1"],
}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """{(env, "straight" or "killed"): (result, cwd)}; a killed run's result is (finished before the kill,
    the resumed run's result)."""
    italy = f1_track_file(tmp_path_factory.mktemp("tracks"), ["Italy"], "italy", frames=100)
    configs = {**CONFIGS, "carracing": [*CONFIGS["carracing"], "--f1-tracks", italy]}
    cwds = {(env, kind): tmp_path_factory.mktemp(f"{env}-{kind}") for env in configs for kind in ("killed", "straight")}
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        futures = {(env, kind): pool.submit(kill_and_resume if kind == "killed" else run, "plr.py", configs[env], cwds[env, kind])
                   for env, kind in cwds}
        return {key: (future.result(), cwds[key]) for key, future in futures.items()}


@pytest.mark.parametrize("env", list(CONFIGS))
def test_killed_plr_run_resumes_to_the_same_result(finished, env):
    """Catches any state a CarRacing or walker run keeps outside its checkpoint (a normalizer's moments,
    a generator, the buffer), or restores wrongly: the resumed run would drift from the straight one."""
    (ended_early, resumed), cwd = finished[env, "killed"]
    straight, straight_cwd = finished[env, "straight"]
    assert straight.returncode == 0, straight.stderr[-3000:]
    assert not ended_early, "the run ended before it could be killed"
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    resumed_at = re.search(r"resuming .* at update (\d+),", resumed.stdout)
    assert resumed_at and 2 <= int(resumed_at.group(1)) <= 12, resumed.stdout[:300]  # updates left to replay
    run_dir, straight_dir = only_run_dir(cwd), only_run_dir(straight_cwd)
    expected, got = read_metrics(straight_dir), read_metrics(run_dir)
    assert [int(r["update"]) for r in expected] == list(range(1, 13))
    drop = lambda rows: [{k: v for k, v in r.items() if k != "sps"} for r in rows]  # noqa: E731
    assert drop(got) == drop(expected)
    with open(os.path.join(run_dir, "eval.json")) as f, open(os.path.join(straight_dir, "eval.json")) as g:
        assert json.load(f) == json.load(g)
