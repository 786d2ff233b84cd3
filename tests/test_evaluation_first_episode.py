"""The held-out evaluation's rule (envs/evaluation.py): each env copy's first episode counts, played to
its own end, whatever the copies stepped alongside it do afterwards. A stand-in env of known episode
lengths per copy makes every return known."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import envs
from envs import evaluation
from envs.levels import HeldOutLevel

# Copy i's episodes last LENGTHS[i] steps each. A step pays 1 in a copy's first episode and 10 in every
# later one: the first episodes return (1, 3, 2), and any later episode counted shows.
LENGTHS = np.array([1, 3, 2])


class EpisodesOfKnownLength:
    """Copies that restart by themselves at each episode end (as the envs do); copy 2's episodes end at
    its step limit (truncated), the others' terminate."""

    solved_threshold = 1.5

    def __init__(self):
        self.steps_taken = 0

    def test_levels(self):
        return {"short": HeldOutLevel(lambda n, rng: None, 100), "also_short": HeldOutLevel(lambda n, rng: None, 100)}

    def reset(self, levels, max_steps):
        self.t = np.zeros(len(LENGTHS), int)
        self.episode = np.zeros(len(LENGTHS), int)
        return {"x": np.zeros((len(LENGTHS), 1), np.float32)}

    def step(self, action):
        self.steps_taken += 1
        reward = np.where(self.episode == 0, 1.0, 10.0)
        self.t += 1
        ended = self.t == LENGTHS
        self.episode[ended] += 1
        self.t[ended] = 0
        truncated = ended & (np.arange(len(LENGTHS)) == 2)
        return {"x": np.zeros((len(LENGTHS), 1), np.float32)}, reward, ended & ~truncated, truncated, {}

    def close(self):
        """Nothing to release (the evaluation closes every env it makes)."""


class IdleAgent:
    def initial_state(self, n, device):
        return None

    def get_action_and_value(self, obs, state, done):
        n = len(done)
        return torch.zeros(n, dtype=torch.long), torch.zeros(n), torch.zeros(n), torch.zeros(n), state


@pytest.fixture
def played(monkeypatch):
    """Every env the evaluation makes is an EpisodesOfKnownLength; the list holds them."""
    made = []

    def make(name, num_envs, seed):
        made.append(EpisodesOfKnownLength())
        return made[-1]

    monkeypatch.setattr(envs, "make", make)
    return made


def test_each_copy_counts_its_first_episode_only(played):
    """Catches counting every episode (or whichever finish first) instead of each copy's first: copy 0
    finishes two more episodes (10 each) and copy 2 starts another while copy 1 plays its first."""
    returns = evaluation.evaluate(IdleAgent(), "stand-in", HeldOutLevel(lambda n, rng: None, 100), 3, seed=0, device="cpu")
    assert returns.tolist() == [1.0, 3.0, 2.0]
    assert played[-1].steps_taken == 3  # until the longest first episode ends, and no longer


def test_solved_rate_and_mean_return_are_over_first_episodes(played):
    """The same rule through evaluate_all: solved above 1.5 by copies 1 and 2, mean return 2."""
    results = evaluation.evaluate_all(IdleAgent(), "stand-in", ["short", "also_short"], 3, seed=0, device="cpu")
    for name in ("short", "also_short"):
        assert results[name]["solved_rate"] == pytest.approx(2 / 3)
        assert results[name]["mean_return"] == pytest.approx(2.0)
