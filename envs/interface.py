"""The env interface, written down once: what the six algorithm scripts use of an env.

`envs.make(name, num_envs, seed)` returns an `Env`: the maze (envs/maze/env.py), CarRacing
(envs/carracing/env.py) and the walker (envs/walker/env.py) each implement every member below, and the scripts
and envs/evaluation.py use nothing else, so a new env that implements these runs under every script once
registered in envs.REGISTRY.
`env.teacher()` returns a `TeacherMDP`, PAIRED's adversary environment.
An env's REGISTRY entry may also name a player of the student's whole rollouts on a GPU (the maze's is
envs/maze/on_device.py); without one, or on a CPU, the scripts play their rollouts with `reset` and `step`.

Levels travel as a level batch: a dataclass of numpy arrays with one row per level (envs/levels.py's
LevelBatch), the env's own `Levels` class. Each env runs `num_envs` copies at once; copy i plays row i
of the batch given to `reset`, and every array of a step has the copies on its first axis.
"""

from __future__ import annotations

from typing import Callable, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
from torch import nn

from envs.levels import HeldOutLevels, LevelBatch


@runtime_checkable
class TeacherMDP(Protocol):
    """PAIRED's adversary MDP: it designs n levels in lockstep, one design step per `step`."""

    num_steps: int
    """Design steps per level (the teacher network's episode length)."""
    action_space: gym.spaces.Space
    """The space of one design action (per level)."""

    def reset(self, n: int) -> dict:
        """Start designing n levels; -> the first observation, a dict of arrays [n, ...]."""

    def step(self, actions: np.ndarray) -> tuple[dict, bool]:
        """Apply one design action per level; -> (observation, done after the last design step)."""

    def levels(self) -> LevelBatch:
        """The designed levels, once done."""


@runtime_checkable
class Env(Protocol):
    """A vectorized UPOMDP: num_envs copies, each playing the level it was reset on, restarting it at
    once when an episode ends."""

    num_envs: int
    """The number of copies stepped together."""
    rng: np.random.Generator
    """The env's own random stream (random start directions, the teacher MDP's noise); checkpointed."""
    single_observation_space: gym.spaces.Dict
    """One copy's student observation: a dict of arrays."""
    single_action_space: gym.spaces.Space
    """One copy's student action."""
    Levels: type[LevelBatch]
    """The level batch class, e.g. to load a level buffer from a checkpoint."""
    Student: type[nn.Module]
    """The paper's student network class, built as Student() (the interface of envs/nets.py); its
    `is_recurrent` decides how PPO splits minibatches."""
    Teacher: type[nn.Module]
    """The paper's adversary network class, built as Teacher(num_steps, **options)."""
    solved_threshold: float
    """An episode with a return above this solved its level."""
    validation_levels: tuple[str, ...]
    """Names of test_levels() evaluated during training."""
    level_metric_names: tuple[str, ...]
    """The keys of level_metrics(), in the order runs log them."""
    level_generators: dict[str, Callable[[int, np.random.Generator], LevelBatch]]
    """name -> generate(n, rng): the generators a script can start from (DR's "random", ACCEL's own)."""
    training: bool
    """True while training; evaluation sets it False to turn off training-only reward shaping."""

    def reset(self, levels: LevelBatch, max_steps: int | None = None) -> dict:
        """Copy i now plays levels[i] (num_envs levels) until max_steps (None: the training limit); -> first observations."""

    def step(self, actions: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, dict]:
        """Step every copy; -> observations, rewards, terminated, truncated [num_envs] and an info dict."""

    def close(self) -> None:
        """Release what the env holds (safe to call twice)."""

    def random_levels(self, n: int, rng: np.random.Generator) -> LevelBatch:
        """Domain randomization's generator: n random levels drawn from rng."""

    def mutate(self, levels: LevelBatch, rng: np.random.Generator, num_edits: int) -> LevelBatch:
        """ACCEL's editor: a child of each level, num_edits random edits away; the parents are untouched."""

    def draw_starts(self, levels: LevelBatch) -> LevelBatch:
        """The levels with every random part of their start drawn now, so two students play the same start."""

    def optimal_returns(self, levels: LevelBatch) -> np.ndarray | None:
        """Each level's best achievable return (for the true regret), or None where the env has no solver."""

    def test_levels(self) -> HeldOutLevels:
        """The held-out levels by name, each generate(n, rng) and its max_steps (the env module's held_out_levels)."""

    def level_metrics(self, levels: LevelBatch) -> dict[str, np.ndarray]:
        """Per-level descriptive metrics by name (level_metric_names), one value per level."""

    def render(self, levels: LevelBatch) -> np.ndarray:
        """RGB images [B, H, W, 3] uint8 of the levels, for the levels_*.png grids."""

    def render_trajectory(self, level: LevelBatch, positions: np.ndarray) -> np.ndarray:
        """One level's image [H, W, 3] (level: a batch of one) with a path of positions [T, 2] (x, y) drawn on it."""

    def agent_positions(self) -> np.ndarray:
        """Where each copy's agent is now, [N, 2] (x, y) in the units render_trajectory draws."""

    def teacher(self) -> TeacherMDP:
        """PAIRED's adversary MDP, its noise drawn from rng."""
