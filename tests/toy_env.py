"""A toy env that implements the whole env interface (envs/interface.py) in one module, as a new env would:
a 1-D corridor whose level is where its goal lies. Registering it is one entry in envs.REGISTRY
(`register`), after which every script's --env offers it. tests/test_toy_env.py trains it under all six
scripts and evaluates it.

The agent starts at 0 and moves by its action, clipped to [-1, 1], each step; reaching the goal ends the
episode with reward 1, and each step costs 0.01. Observation: {"state": [position, goal] / LENGTH}.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import torch
from torch import nn
from torch.distributions import Independent, Normal

import envs
from envs.levels import HeldOutLevel, HeldOutLevels, LevelBatch
from envs.nets import FeedForwardActorCritic, layer_init

LENGTH = 10.0  # the corridor: positions 0 .. LENGTH
MAX_STEPS = 30  # the training episode limit
NOISE_DIM = 4  # the teacher's noise
IMAGE_WIDTH = 64


@dataclasses.dataclass
class ToyLevels(LevelBatch):
    goal: np.ndarray  # float64 [B], in [1, LENGTH]


def toy_levels(goals) -> ToyLevels:
    return ToyLevels(np.asarray(goals, dtype=np.float64))


class ToyTeacherMDP:
    """One design step: the action in [-1, 1] places the goal between 1 and LENGTH."""

    num_steps = 1
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def reset(self, n: int) -> dict:
        self.n, self.goals = n, np.full(n, 1.0)
        return {"noise": self.rng.random((n, NOISE_DIM), dtype=np.float32), "time": np.zeros(n, dtype=np.int64)}

    def step(self, actions: np.ndarray) -> tuple[dict, bool]:
        self.goals = 1.0 + (np.clip(np.asarray(actions, dtype=np.float64).reshape(self.n), -1, 1) + 1) / 2 * (LENGTH - 1)
        return {"noise": self.rng.random((self.n, NOISE_DIM), dtype=np.float32), "time": np.zeros(self.n, dtype=np.int64)}, True

    def levels(self) -> ToyLevels:
        return toy_levels(self.goals)


def mlp(inputs: int, outputs: int, gain: float) -> nn.Sequential:
    return nn.Sequential(layer_init(nn.Linear(inputs, 16)), nn.Tanh(), layer_init(nn.Linear(16, outputs), gain=gain))


class ToyStudent(FeedForwardActorCritic):
    """[position, goal] -> a Gaussian step and a value."""

    def __init__(self):
        super().__init__()
        self.actor_mean, self.critic = mlp(2, 1, 0.01), mlp(2, 1, 1.0)
        self.actor_logstd = nn.Parameter(torch.zeros(1))

    def dist_and_value(self, obs: dict, state=None, done=None):
        x = obs["state"].float()
        mean = self.actor_mean(x)
        return Independent(Normal(mean, self.actor_logstd.exp().expand_as(mean)), 1), self.critic(x).squeeze(-1)


class ToyTeacher(FeedForwardActorCritic):
    """The noise -> a Gaussian goal placement and a value."""

    def __init__(self, num_steps: int):
        super().__init__()
        self.actor_mean, self.critic = mlp(NOISE_DIM, 1, 0.01), mlp(NOISE_DIM, 1, 1.0)
        self.actor_logstd = nn.Parameter(torch.zeros(1))

    def dist_and_value(self, obs: dict, state=None, done=None):
        x = obs["noise"].float()
        mean = self.actor_mean(x)
        return Independent(Normal(mean, self.actor_logstd.exp().expand_as(mean)), 1), self.critic(x).squeeze(-1)


class ToyEnv:
    """num_envs corridors stepped together; a copy restarts its level as soon as an episode ends."""

    def __init__(self, num_envs: int, seed: int):
        self.num_envs = num_envs
        self.rng = np.random.default_rng(seed)
        self.single_observation_space = gym.spaces.Dict({"state": gym.spaces.Box(0.0, 1.0, (2,), np.float32)})
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.Levels, self.Student, self.Teacher = ToyLevels, ToyStudent, ToyTeacher
        self.solved_threshold = 0.0
        self.validation_levels = ("Near",)
        self.level_metric_names = ("goal",)
        self.level_generators = {"random": self.random_levels}
        self.training = True

    def reset(self, levels: ToyLevels, max_steps: int | None = None) -> dict:
        self.goals, self.max_steps = levels.goal.copy(), max_steps or MAX_STEPS
        self.positions, self.steps = np.zeros(self.num_envs), np.zeros(self.num_envs, dtype=np.int64)
        return self.observation()

    def observation(self) -> dict:
        return {"state": (np.stack([self.positions, self.goals], 1) / LENGTH).astype(np.float32)}

    def step(self, actions: np.ndarray):
        self.positions = np.clip(self.positions + np.clip(actions.reshape(self.num_envs), -1, 1), 0, LENGTH)
        self.steps += 1
        terminated = self.positions >= self.goals
        truncated = ~terminated & (self.steps >= self.max_steps)
        rewards = np.where(terminated, 1.0, -0.01)
        ended = terminated | truncated
        self.positions[ended], self.steps[ended] = 0.0, 0
        return self.observation(), rewards, terminated, truncated, {}

    def close(self) -> None:
        """Nothing to release."""

    def random_levels(self, n: int, rng: np.random.Generator) -> ToyLevels:
        return toy_levels(rng.uniform(1.0, LENGTH, n))

    def mutate(self, levels: ToyLevels, rng: np.random.Generator, num_edits: int) -> ToyLevels:
        return toy_levels(np.clip(levels.goal + rng.normal(0.0, 0.5, (num_edits, len(levels))).sum(0), 1.0, LENGTH))

    def draw_starts(self, levels: ToyLevels) -> ToyLevels:
        return levels.copy()  # nothing random at the start

    def optimal_returns(self, levels: ToyLevels) -> None:
        return None  # no solver

    def test_levels(self) -> HeldOutLevels:
        return HeldOutLevels({name: HeldOutLevel(lambda n, rng, goal=goal: toy_levels(np.full(n, goal)), MAX_STEPS)
                              for name, goal in (("Near", 2.0), ("Far", 8.0))})

    def level_metrics(self, levels: ToyLevels) -> dict[str, np.ndarray]:
        return {"goal": levels.goal.copy()}

    def render(self, levels: ToyLevels) -> np.ndarray:
        images = np.full((len(levels), 8, IMAGE_WIDTH, 3), 255, dtype=np.uint8)
        images[np.arange(len(levels)), :, self.column(levels.goal)] = (40, 200, 60)
        return images

    def render_trajectory(self, level: ToyLevels, positions: np.ndarray) -> np.ndarray:
        image = self.render(level)[0]
        image[3:5, self.column(positions[:, 0])] = (230, 40, 40)
        return image

    def agent_positions(self) -> np.ndarray:
        return np.stack([self.positions, np.zeros(self.num_envs)], 1)

    def teacher(self) -> ToyTeacherMDP:
        return ToyTeacherMDP(self.rng)

    @staticmethod
    def column(x) -> np.ndarray:
        return np.clip((np.asarray(x) / LENGTH * (IMAGE_WIDTH - 1)).round().astype(np.int64), 0, IMAGE_WIDTH - 1)


def register() -> None:
    """The one registry entry that adds the env to every script."""
    envs.REGISTRY["toy"] = envs.Registered("toy_env:ToyEnv", evaluation_episodes=2)
