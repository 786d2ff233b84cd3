"""The curators' gate on gradient steps, seen from outside their main loops: Robust PLR, ACCEL and
PAIRED+Evo step on replayed levels only, so their students' weights are unchanged across every update on
new levels (ACCEL's and PAIRED+Evo's children too); PLR and DR step on every update. Each script runs in
this process with a checkpoint every update, each checkpoint's weights kept as written."""

from __future__ import annotations

import csv
import os
import runpy
import sys

import numpy as np
import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# plr.py: UPDATES updates of 2 x 16 steps; a buffer of 2 levels is full after update 1, so replays start at update 2.
UPDATES = 12
TINY = ["--env", "maze", "--num-envs", "2", "--num-steps", "16", "--level-buffer-size", "2", "--total-timesteps", str(UPDATES * 32),
        "--eval-episodes", "0", "--checkpoint-interval", "1", "--levels-interval", "1000", "--log-interval", "1000"]
# script, flags, the students it trains (their checkpoint keys, with "<name>_optimizer" or "optimizer"),
# whether it steps on replayed levels only
CURATORS = {
    "Robust PLR": ("plr.py", [], ["agent"], True),
    "PLR": ("plr.py", ["--no-robust"], ["agent"], False),
    "DR": ("plr.py", ["--replay-prob", "0"], ["agent"], False),
    "ACCEL": ("accel.py", [], ["agent"], True),
    "PAIRED+Evo": ("paired_evo.py", ["--replay-prob", "0.5"], ["protagonist", "antagonist"], True),
}


def run_keeping_checkpoints(script, flags, students, cwd, monkeypatch):
    """Run the script here; returns its metric rows and, per update, each student's weights and whether
    its Adam holds any state (it has none before its first step) as checkpointed after that update."""
    kept = {}
    save = torch.save

    def save_and_keep(state, path):
        optimizer = {name: state["optimizer" if name == "agent" else f"{name}_optimizer"] for name in students}
        kept[state["update"]] = {name: ({k: v.clone() for k, v in state[name].items()}, bool(optimizer[name]["state"]))
                                 for name in students}
        save(state, path)

    monkeypatch.setattr(torch, "save", save_and_keep)
    monkeypatch.setattr(sys, "argv", [script, *TINY, *flags])
    monkeypatch.chdir(cwd)
    numpy_state = np.random.get_state()
    with torch.random.fork_rng():  # the script seeds the global generators: leave the other tests' alone
        runpy.run_path(os.path.join(ROOT, script), run_name="__main__")
    np.random.set_state(numpy_state)
    (run_dir,) = os.listdir(cwd / "runs")
    with open(cwd / "runs" / run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f)), kept


@pytest.mark.parametrize("curator", list(CURATORS))
def test_weights_change_exactly_on_the_updates_that_train(tmp_path, monkeypatch, curator):
    """Catches a broken gate: a curator stepping on new levels (or on its children) where it must not, or
    never training (which a loss column alone would not show), and plr.py's `trained` column not being
    Robust PLR's replay flag. A new-level update right after a replay one shows that no optimizer step ran
    at all (Adam's momentum would move the weights even without a gradient)."""
    script, flags, students, replay_only = CURATORS[curator]
    rows, kept = run_keeping_checkpoints(script, flags, students, tmp_path, monkeypatch)
    updates = len(rows)  # ACCEL's and PAIRED+Evo's budgets count their other rollouts' steps too: fewer updates
    assert updates >= 6 and [int(r["update"]) for r in rows] == list(range(1, updates + 1)) == sorted(kept)
    replay = [r["replay"] == "1" for r in rows]
    trained = replay if replay_only else [True] * updates
    if script == "plr.py":
        assert [r["trained"] == "1" for r in rows] == trained
    for name in students:
        assert kept[1][name][1] == trained[0]  # Adam's state exists once it has stepped
        for update in range(2, updates + 1):
            before, after = kept[update - 1][name][0], kept[update][name][0]
            changed = any(not torch.equal(before[k], after[k]) for k in after)
            assert changed == trained[update - 1], f"{name}, update {update}: trained {trained[update - 1]}, weights changed {changed}"
    if replay_only:
        successive = set(zip(replay, replay[1:]))
        assert (False, True) in successive and (True, False) in successive, "the run needs both kinds of update in turn"


@pytest.mark.parametrize("curator", ["Robust PLR", "ACCEL", "PAIRED+Evo"])
def test_every_replayed_level_is_rescored(tmp_path, monkeypatch, curator):
    """A replay update scores the levels it replayed anew (Robust PLR's and ACCEL's buffer keeps the latest
    score of a level, not the one it entered with): the script's LevelBuffer.update_scores runs once per
    replay update, on exactly the replayed levels, and the buffer then holds those scores. Catches a
    curator that never rescores what it replays, whose buffer keeps sampling stale scores."""
    sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
    from gpu_check import run_script

    script, flags, _, _ = CURATORS[curator]
    rescored = []

    def instrument(namespace):
        buffer_class = namespace["LevelBuffer"]
        update_scores = buffer_class.update_scores

        def recording(buffer, index, scores):
            update_scores(buffer, index, scores)
            rescored.append((np.array(index), np.array(scores), buffer.scores[index].copy()))
        monkeypatch.setattr(buffer_class, "update_scores", recording)

    monkeypatch.chdir(tmp_path)
    numpy_state = np.random.get_state()
    with torch.random.fork_rng():  # the script seeds the global generators: leave the other tests' alone
        run_script(os.path.join(ROOT, script), [*TINY, *flags], instrument)
    np.random.set_state(numpy_state)
    (run_dir,) = os.listdir(tmp_path / "runs")
    with open(tmp_path / "runs" / run_dir / "metrics.csv", newline="") as f:
        replays = sum(row["replay"] == "1" for row in csv.DictReader(f))
    assert replays >= 2 and len(rescored) == replays
    for index, scores, held in rescored:  # the run's 2 copies; a level sampled twice keeps its last score
        latest = dict(zip(index.tolist(), scores))
        assert len(index) == 2 and np.array_equal(held, np.array([latest[i] for i in index.tolist()], dtype=held.dtype))
