"""Reward normalization for a batch of env copies, as gym's NormalizeReward / VecNormalize wrappers do
for the reference on CarRacing and the walker (`--normalize-returns`, `--normalize-teacher-returns`)."""

from __future__ import annotations

import numpy as np


class ReturnNormalizer:
    """Return normalization (CarRacing, walker): rewards are divided by a running standard deviation of the
    discounted return and clipped to [-10, 10], as gym's VecNormalize does for the reference. The
    running moments are updated with every step's discounted return of every copy. The teacher's
    returns (its final-step regret) are normalized the same way in CarRacing and the walker."""

    def __init__(self, num_envs: int, gamma: float, clip: float = 10.0, epsilon: float = 1e-8):
        self.gamma, self.clip, self.epsilon = gamma, clip, epsilon
        self.returns = np.zeros(num_envs)
        self.mean, self.var, self.count = 0.0, 1.0, 1e-4

    def update(self, values: np.ndarray) -> None:
        """Parallel-algorithm update of the running mean and variance with a batch of values."""
        batch_mean, batch_var, batch_count = values.mean(), values.var(), len(values)
        delta, total = batch_mean - self.mean, self.count + batch_count
        self.mean += delta * batch_count / total
        self.var = (self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total) / total
        self.count = total

    def __call__(self, reward: np.ndarray, ended: np.ndarray) -> np.ndarray:
        self.returns = self.returns * self.gamma + reward
        self.update(self.returns)
        self.returns[ended] = 0.0
        return np.clip(reward / np.sqrt(self.var + self.epsilon), -self.clip, self.clip).astype(np.float32)

    def state_dict(self) -> dict:
        return {"mean": self.mean, "var": self.var, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.var, self.count = state["mean"], state["var"], state["count"]
