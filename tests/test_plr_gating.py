"""plr.py's gate on gradient steps, seen from outside its main loop: Robust PLR steps on replayed levels
only, so its weights are unchanged across every update on new levels; PLR and DR step on every update.
plr.py runs in this process with a checkpoint every update, each checkpoint's weights kept as written."""

from __future__ import annotations

import csv
import os
import runpy
import sys

import numpy as np
import pytest
import torch

SCRIPT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "plr.py")
# UPDATES updates of 2 x 16 steps; a buffer of 2 levels is full after update 1, so replays start at update 2.
UPDATES = 12
TINY = ["--env", "maze", "--num-envs", "2", "--num-steps", "16", "--level-buffer-size", "2", "--total-timesteps", str(UPDATES * 32),
        "--eval-episodes", "1", "--eval-interval", "1000", "--checkpoint-interval", "1", "--levels-interval", "1000",
        "--log-interval", "1000"]


def run_keeping_checkpoints(flags, cwd, monkeypatch):
    """Run plr.py here; returns its metric rows and, per update, the agent's weights and whether Adam
    holds any state (it has none before its first step) as checkpointed after that update."""
    kept = {}
    save = torch.save

    def save_and_keep(state, path):
        kept[state["update"]] = ({k: v.clone() for k, v in state["agent"].items()}, bool(state["optimizer"]["state"]))
        save(state, path)

    monkeypatch.setattr(torch, "save", save_and_keep)
    monkeypatch.setattr(sys, "argv", [SCRIPT, *TINY, *flags])
    monkeypatch.chdir(cwd)
    numpy_state = np.random.get_state()
    with torch.random.fork_rng():  # the script seeds the global generators: leave the other tests' alone
        runpy.run_path(SCRIPT, run_name="__main__")
    np.random.set_state(numpy_state)
    (run_dir,) = os.listdir(cwd / "runs")
    with open(cwd / "runs" / run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f)), kept


@pytest.mark.parametrize("flags, robust", [([], True), (["--no-robust"], False), (["--replay-prob", "0"], False)],
                         ids=["Robust PLR", "PLR", "DR"])
def test_weights_change_exactly_on_the_updates_that_train(tmp_path, monkeypatch, flags, robust):
    """Catches a broken gate: Robust PLR stepping on new levels, or any mode never training (which the
    `trained` column alone would not show), and a `trained` column that is not Robust PLR's replay flag.
    A new-level update right after a replay one shows that no optimizer step ran at all (Adam's momentum
    would move the weights even without a gradient)."""
    rows, kept = run_keeping_checkpoints(flags, tmp_path, monkeypatch)
    assert [int(r["update"]) for r in rows] == list(range(1, UPDATES + 1)) and sorted(kept) == list(range(1, UPDATES + 1))
    trained = [r["trained"] == "1" for r in rows]
    replay = [r["replay"] == "1" for r in rows]
    assert trained == (replay if robust else [True] * UPDATES)
    assert kept[1][1] == trained[0]  # Adam's state exists once it has stepped
    for update in range(2, UPDATES + 1):
        before, after = kept[update - 1][0], kept[update][0]
        changed = any(not torch.equal(before[k], after[k]) for k in after)
        assert changed == trained[update - 1], f"update {update}: trained {trained[update - 1]}, weights changed {changed}"
    if robust:
        successive = set(zip(replay, replay[1:]))
        assert (False, True) in successive and (True, False) in successive, "the run needs both kinds of update in turn"
