"""envs/training_run.py's parts on small cases: what a checkpoint keeps of each piece of a script's state, and
the timers of an update. (Whole runs killed and resumed: test_scripts_resume.py, test_continue_run.py.)"""

from __future__ import annotations

import time

import numpy as np
import pytest
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
