"""Reward scaling for PPO: divide by the running standard deviation of the discounted return,
then clip. The forward task's reward ``exp(1/d) - 30`` is about -27 far from the block and
tens of thousands when touching it; unscaled, those steps would wreck the value loss."""

from __future__ import annotations

import numpy as np


class RunningMeanStd:
    """Parallel (Chan et al.) running mean and variance of a scalar stream."""

    def __init__(self) -> None:
        self.mean = 0.0
        self.var = 1.0
        self.count = 1e-4

    def update(self, values: np.ndarray) -> None:
        batch_mean, batch_var, batch_count = float(values.mean()), float(values.var()), values.size
        delta = batch_mean - self.mean
        total = self.count + batch_count
        self.mean += delta * batch_count / total
        m2 = (self.var * self.count + batch_var * batch_count
              + delta**2 * self.count * batch_count / total)
        self.var = m2 / total
        self.count = total


class RewardScaler:
    """One discounted-return accumulator per env; rewards are scaled by its running std."""

    def __init__(self, num_envs: int, gamma: float, clip: float, epsilon: float = 1e-8) -> None:
        self.returns = np.zeros(num_envs)
        self.gamma = gamma
        self.clip = clip
        self.epsilon = epsilon
        self.stats = RunningMeanStd()

    def __call__(self, rewards: np.ndarray, done: np.ndarray) -> np.ndarray:
        self.returns = self.returns * self.gamma + rewards
        self.stats.update(self.returns)
        scaled = rewards / np.sqrt(self.stats.var + self.epsilon)
        self.returns[done] = 0.0
        return np.clip(scaled, -self.clip, self.clip)

    @property
    def scale(self) -> float:
        return float(np.sqrt(self.stats.var + self.epsilon))

    def state_dict(self) -> dict[str, float]:
        return {"mean": self.stats.mean, "var": self.stats.var, "count": self.stats.count}

    def load_state_dict(self, state: dict[str, float]) -> None:
        self.stats.mean, self.stats.var, self.stats.count = (
            float(state["mean"]), float(state["var"]), float(state["count"])
        )
