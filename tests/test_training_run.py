"""envs/training_run.py's parts on small cases: what a checkpoint keeps of each piece of a script's state, the
timers of an update, and a run given --eval-episodes 0. (Whole runs killed and resumed: test_scripts_resume.py,
test_continue_run.py.)"""

from __future__ import annotations

import csv
import os
import time

import numpy as np
import pytest
import script_runs
import torch

from envs.normalize import ReturnNormalizer
from envs.training_run import Timers, load_state, state_of


def test_every_kind_of_state_comes_back_as_it_was_saved():
    """A net, its optimizer, a normalizer, generators nested in a dict and an absent piece (None), as the
    scripts name them: after a round trip through state_of and load_state, fresh pieces equal the saved."""
    def pieces(seed):
        torch.manual_seed(seed)
        net = torch.nn.Linear(3, 2)
        optimizer = torch.optim.Adam(net.parameters(), lr=0.1)
        normalizer = ReturnNormalizer(2, 0.99)
        return {"agent": net, "optimizer": optimizer, "normalizer": normalizer, "absent": None,
                "rng": {"level": np.random.default_rng(seed), "env": np.random.default_rng(seed + 10)}}

    saved = pieces(0)
    saved["agent"](torch.ones(1, 3)).sum().backward()
    saved["optimizer"].step()
    saved["normalizer"](np.array([1.0, 2.0]), np.array([False, True]))
    saved["rng"]["level"].random(5)
    kept = state_of(saved)
    assert kept["absent"] is None and set(kept["rng"]) == {"level", "env"}

    restored = pieces(1)
    load_state(restored, kept)
    assert torch.equal(restored["agent"].weight, saved["agent"].weight)
    assert restored["optimizer"].state_dict()["state"][0]["step"] == 1
    assert restored["normalizer"].var == pytest.approx(saved["normalizer"].var)
    assert restored["rng"]["level"].random() == saved["rng"]["level"].random()
    assert restored["rng"]["env"].random() == saved["rng"]["env"].random()


def test_timers_add_up_each_part_and_give_its_share():
    timers = Timers("rollout", "update")
    for _ in range(2):
        with timers("rollout"):
            time.sleep(0.02)
    with timers("update"):
        time.sleep(0.04)
    columns = timers.columns()
    assert list(columns) == ["time_rollout", "time_update"]
    assert columns["time_rollout"] >= 0.04 and columns["time_update"] >= 0.04
    assert timers.shares().startswith("rollout ") and ", update " in timers.shares()


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# plr.py with every episode an evaluation plays counted (envs/evaluation.py's play_first_episodes plays them all).
COUNTING_EVALUATIONS = f"""
import runpy, sys
import envs.evaluation
played = []
play = envs.evaluation.play_first_episodes
envs.evaluation.play_first_episodes = lambda *args, **kwargs: played.append(1) or play(*args, **kwargs)
sys.argv = ["plr.py", *sys.argv[1:]]
try:
    runpy.run_path({os.path.join(ROOT, "plr.py")!r}, run_name="__main__")
finally:
    print(f"evaluations played: {{len(played)}}")
"""


def test_eval_episodes_0_plays_no_evaluation(tmp_path):
    """Catches a run that validates (every update, as --eval-interval 1 asks) or evaluates at its end when
    told --eval-episodes 0: something played, eval.json written or a val_* column filled."""
    result = script_runs.run(["-c", COUNTING_EVALUATIONS, "--env", "maze", "--num-envs", "4", "--num-steps", "32",
                              "--total-timesteps", "256", "--level-buffer-size", "8", "--eval-episodes", "0",
                              "--eval-interval", "1", "--levels-interval", "100", "--no-cuda"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert "evaluations played: 0" in result.stdout and "no evaluation (--eval-episodes 0)" in result.stdout
    assert "validation:" not in result.stdout
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert not [name for name in os.listdir(run_dir) if name.startswith("eval")]
    assert os.path.isfile(run_dir / "checkpoint.pt") and os.path.isfile(run_dir / "curves.png")  # the run went to its end
    with open(run_dir / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 and all(row["val_solved_rate"] == row["val_return"] == "" for row in rows)
