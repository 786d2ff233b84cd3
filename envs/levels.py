"""Level batches: what a teacher proposes and a level buffer stores, for every env; and the held-out
levels of the zero-shot benchmark.

A batch of levels is a dataclass whose fields are numpy arrays sharing their first axis (one row per
level). `LevelBatch` gives every such dataclass slicing, in-place assignment and concatenation, so a
level buffer of 4000-10000 levels (each curator script's `LevelBuffer`) is a handful of arrays, cheap to
index and to save in a checkpoint.
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
