"""The maze's level batch and the grid helpers its generators share: what envs/maze/env.py (the env, the
teacher, DR, mutation) and envs/maze/held_out.py (the held-out mazes) both build levels from.

Coordinates are (x, y): x the column from the left, y the row from the top, outer wall ring included.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from envs.levels import LevelBatch


@dataclasses.dataclass
class MazeLevels(LevelBatch):
    """A batch of mazes: walls [B, H, W] bool (outer ring included), goal and agent start [B, 2] as
    (x, y), and the start direction [B] (0 east, 1 south, 2 west, 3 north; RANDOM_DIRECTION, -1: drawn
    when the level is reset)."""

    walls: np.ndarray
    goal: np.ndarray
    agent: np.ndarray
    agent_dir: np.ndarray

    @property
    def size(self) -> tuple[int, int]:
        return self.walls.shape[1], self.walls.shape[2]


def empty_grid(n: int, size: int) -> np.ndarray:
    """n grids of size x size with only the outer wall ring."""
    walls = np.zeros((n, size, size), dtype=bool)
    walls[:, [0, -1], :] = True
    walls[:, :, [0, -1]] = True
    return walls


def random_free_cells(free: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One uniformly random True cell per grid of free [B, H, W], as (x, y) [B, 2]."""
    flat = np.where(free.reshape(len(free), -1), rng.random(free.reshape(len(free), -1).shape), -1.0)
    index = flat.argmax(axis=1)
    return np.stack([index % free.shape[2], index // free.shape[2]], axis=1)
