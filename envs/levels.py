"""Level batches: what a teacher proposes and a level buffer stores, for every env; and the level buffer
of the curators (plr.py, accel.py, paired_evo.py).

A batch of levels is a dataclass whose fields are numpy arrays sharing their first axis (one row per
level). `LevelBatch` gives every such dataclass slicing, in-place assignment and concatenation, so a
level buffer of 4000-10000 levels is a handful of arrays, cheap to index and to save in a checkpoint.
`LevelBuffer` is Robust PLR's buffer (Jiang et al. 2021): levels, their scores, their staleness and
their highest return so far, replayed by rank and staleness.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np


class LevelBatch:
    """Mixin for a dataclass of arrays with one row per level."""

    def __len__(self) -> int:
        return len(getattr(self, dataclasses.fields(self)[0].name))

    def __getitem__(self, index):
        index = np.atleast_1d(index) if np.isscalar(index) else index
        return type(self)(**{f.name: getattr(self, f.name)[index] for f in dataclasses.fields(self)})

    def __setitem__(self, index, other) -> None:
        index = np.atleast_1d(index) if np.isscalar(index) else index
        for f in dataclasses.fields(self):
            getattr(self, f.name)[index] = getattr(other, f.name)

    @classmethod
    def concat(cls, batches):
        return cls(**{f.name: np.concatenate([getattr(b, f.name) for b in batches]) for f in dataclasses.fields(cls)})

    def copy(self):
        return type(self)(**{f.name: getattr(self, f.name).copy() for f in dataclasses.fields(self)})

    def state_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_state_dict(cls, state: dict):
        return cls(**{f.name: np.asarray(state[f.name]) for f in dataclasses.fields(cls)})


@dataclasses.dataclass
class HeldOutLevel:
    """One held-out level of the zero-shot benchmark.

    `generate(n, rng)` returns n levels (a fixed layout repeated, or n fresh draws of a procedural one);
    `max_steps` is the episode limit this level is evaluated with.
    """

    generate: Callable[[int, np.random.Generator], LevelBatch]
    max_steps: int


class HeldOutLevels(dict):
    """An env's held-out set, name -> HeldOutLevel in the benchmark's order: what `env.test_levels()`
    returns for every env, each built by its env module's `held_out_levels`. Looking up an unknown name
    raises ValueError listing the known ones (one line, for a command-line error)."""

    def __missing__(self, name):
        raise ValueError(f"unknown held-out level {name!r}: expected one of {', '.join(self)}")


def rank_weights(scores: np.ndarray, temperature: float) -> np.ndarray:
    """P_S: proportional to (1 / rank)^(1 / T), rank 1 the highest score."""
    ranks = np.empty(len(scores))
    ranks[np.argsort(-scores, kind="stable")] = np.arange(1, len(scores) + 1)
    weights = (1.0 / ranks) ** (1.0 / temperature)
    return weights / weights.sum()


def staleness_weights(last_sampled: np.ndarray, update: int) -> np.ndarray:
    """P_C: proportional to the updates since each level was last sampled (uniform if all fresh)."""
    staleness = (update - last_sampled).astype(np.float64)
    total = staleness.sum()
    return staleness / total if total > 0 else np.full(len(staleness), 1.0 / len(staleness))


class LevelBuffer:
    """The PLR level buffer: levels, their scores, the update each was last sampled at, and each level's
    highest return so far (MaxMC's record, envs/scores.py; kept whatever the score, for the diagnostic)."""

    def __init__(self, capacity: int, temperature: float, staleness_coef: float):
        self.capacity = capacity
        self.temperature = temperature
        self.staleness_coef = staleness_coef
        self.levels = None
        self.scores = np.zeros(0)
        self.last_sampled = np.zeros(0, dtype=np.int64)
        self.highest_returns = np.zeros(0)

    def __len__(self) -> int:
        return len(self.scores)

    def replay_weights(self, update: int) -> np.ndarray:
        """P = (1 - rho) P_S + rho P_C."""
        return (1 - self.staleness_coef) * rank_weights(self.scores, self.temperature) + self.staleness_coef * staleness_weights(self.last_sampled, update)

    def sample(self, n: int, update: int, rng: np.random.Generator) -> np.ndarray:
        """Indices of n levels drawn from P (with replacement); they become fresh."""
        index = rng.choice(len(self), size=n, p=self.replay_weights(update))
        self.last_sampled[index] = update
        return index

    def update_scores(self, index: np.ndarray, scores: np.ndarray) -> None:
        self.scores[index] = scores

    def raise_highest_returns(self, index: np.ndarray, highest_returns: np.ndarray) -> np.ndarray:
        """Raise the replayed levels' records to the highest returns their copies just reached (a level
        drawn twice keeps the higher of its two); -> the records of index, this rollout included."""
        np.maximum.at(self.highest_returns, index, highest_returns)
        return self.highest_returns[index]

    def insert(self, levels, scores: np.ndarray, update: int, highest_returns: np.ndarray) -> int:
        """Offer new levels one by one: each enters if there is room, or replaces the level of lowest
        replay weight if it scores higher than that level. Returns how many entered."""
        entered = 0
        for i in range(len(scores)):
            if len(self) < self.capacity:
                self.levels = levels[i] if self.levels is None else type(levels).concat([self.levels, levels[i]])
                self.scores = np.append(self.scores, scores[i])
                self.last_sampled = np.append(self.last_sampled, update)
                self.highest_returns = np.append(self.highest_returns, highest_returns[i])
                entered += 1
                continue
            lowest = int(np.argmin(self.replay_weights(update)))
            if scores[i] > self.scores[lowest]:
                self.levels[lowest] = levels[i]
                self.scores[lowest] = scores[i]
                self.last_sampled[lowest] = update
                self.highest_returns[lowest] = highest_returns[i]
                entered += 1
        return entered

    def state_dict(self) -> dict:
        levels = None if self.levels is None else self.levels.state_dict()
        return {"levels": levels, "scores": self.scores, "last_sampled": self.last_sampled, "highest_returns": self.highest_returns}

    def load_state_dict(self, state: dict, level_type) -> None:
        self.levels = None if state["levels"] is None else level_type.from_state_dict(state["levels"])
        self.scores = np.asarray(state["scores"])
        self.last_sampled = np.asarray(state["last_sampled"])
        # (a checkpoint written before the record was kept resumes with the record's start, 0)
        self.highest_returns = np.asarray(state.get("highest_returns", np.zeros(len(self.scores))))
