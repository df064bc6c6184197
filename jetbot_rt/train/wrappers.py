"""The trainer's reward shaping as Gymnasium wrappers (cleanrl's ``make_env`` style).

The registered envs return the task's own reward (what ``eval`` reports); everything a
trainer adds to learn faster lives here, so any trainer (ours, Stable-Baselines3) can reuse
it. Per env: ``RecordEpisodeStatistics`` (the true return, in ``info["episode"]``), an
optional ``symlog`` of the task reward, potential-based progress and aim shaping, a bonus
/ penalty on the step that succeeds / fails and a cost per step. Reward normalisation
(running std of the discounted return) and clipping are vector wrappers, see
``normalize_rewards``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import RecordEpisodeStatistics, TransformReward

from jetbot_rt.config.sections import Config
from jetbot_rt.errors import UsageError
from jetbot_rt.train.env import JetbotEnv

REWARD_TRANSFORMS = ("symlog", "none")


def symlog(reward: SupportsFloat) -> float:
    """``sign(r) ln(1 + |r|)``: compresses forward's reward, -27 .. 2e4, into -3.3 .. 10."""
    r = float(reward)
    return float(np.sign(r) * np.log1p(abs(r)))


class PotentialShaping(gym.Wrapper):
    """Adds ``coef * (phi - phi')`` per step, ``phi = info[key]`` (a distance to shrink).

    Potential-based (Ng et al. 1999): it sums to ``coef * (phi_start - phi_end)`` over an
    episode, so it cannot be farmed by going back and forth, and it does not change which
    policy is optimal. ``phi`` is privileged sim state, used only in the reward: the policy
    still sees only the camera.
    """

    def __init__(self, env: gym.Env, key: str, coef: float) -> None:
        super().__init__(env)
        self.key = key
        self.coef = coef
        self._last = 0.0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        if self.key not in info:  # a task of the user's that reports no such quantity
            raise UsageError(f"the trainer's shaping reads info[{self.key!r}], which this "
                             f"task's outcome does not report (set its coefficient to 0)")
        self._last = float(info[self.key])
        return obs, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        value = float(info[self.key])
        reward = float(reward) + self.coef * (self._last - value)
        self._last = value
        return obs, reward, terminated, truncated, info


class OutcomeBonus(gym.Wrapper):
    """Adds ``success_bonus`` on a step whose ``info["is_success"]`` ends the episode and
    subtracts ``fail_penalty`` on a step whose ``info["failed"]`` does."""

    def __init__(self, env: gym.Env, success_bonus: float, fail_penalty: float) -> None:
        super().__init__(env)
        self.success_bonus = success_bonus
        self.fail_penalty = fail_penalty

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        reward = float(reward)
        if terminated and info.get("is_success"):
            reward += self.success_bonus
        if terminated and info.get("failed"):
            reward -= self.fail_penalty
        return obs, reward, terminated, truncated, info


class StepPenalty(gym.RewardWrapper):
    """Subtracts ``penalty`` on every step: Habitat's slack reward (Savva et al. 2019), a
    cost of time, so that standing still where the goal is unclear is no longer free."""

    def __init__(self, env: gym.Env, penalty: float) -> None:
        super().__init__(env)
        self.penalty = penalty

    def reward(self, reward: SupportsFloat) -> float:
        return float(reward) - self.penalty


class KeepInfo(gym.Wrapper):
    """Passes on only the ``info`` keys a trainer reads. A vector env pickles each env's info
    through a pipe and merges it key by key into arrays every step; PPO reads three keys at
    the end of an episode, and the env's full info (pose, duty, goal, ...) cost the learner
    about a third of its share of a vector step (docs/TRAINING.md, "Speed")."""

    def __init__(self, env: gym.Env, keys: tuple[str, ...]) -> None:
        super().__init__(env)
        self.keys = keys

    def _kept(self, info: dict[str, Any]) -> dict[str, Any]:
        return {k: info[k] for k in self.keys if k in info}

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        return obs, self._kept(info)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self._kept(info)


CRITIC_STATE = "critic_state"
"""The ``info`` key of the privileged state an asymmetric critic reads (``CriticState``)."""


class CriticState(gym.Wrapper):
    """Adds ``info["critic_state"]``: the task's privileged state (``Task.critic_state``) for
    PPO's asymmetric critic (``--critic state``), at the reset and after every step, of the
    state the returned frame shows. The task gets the env's ``info`` plus ``sim_params``
    (this episode's ``[sim]`` knobs; the env reports them at the reset only). A trainer's
    wrapper, as the shaping: the registered env and ``eval`` never compute it, the policy
    never sees it. The vector envs carry it to the learner like any other info key
    (``KeepInfo`` keeps it), a finished episode's in ``final_info``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        task = env.unwrapped.task
        self.size = len(task.critic_state_names)
        if not self.size:
            raise UsageError(f"task {task.name!r} has no privileged critic state "
                             "(Task.critic_state_names is empty)")

    def _with_state(self, info: dict[str, Any]) -> dict[str, Any]:
        env = self.env.unwrapped
        state = env.task.critic_state({**info, "sim_params": env.sim_params})
        vector = None if state is None else np.asarray(state, dtype=np.float32)
        if vector is None or vector.shape != (self.size,) or not np.isfinite(vector).all():
            got = "None" if vector is None else f"shape {list(vector.shape)}" + (
                "" if vector.shape != (self.size,) else " with non-finite values")
            raise UsageError(f"task {env.task.name!r}: critic_state() must return {self.size} "
                             f"finite values (one per critic_state_names), got {got}")
        info[CRITIC_STATE] = vector
        return info

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        return obs, self._with_state(info)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self._with_state(info)


@dataclass(frozen=True)
class Shaping:
    """What ``make_train_env`` adds to the task's reward (``PPOArgs`` holds the same fields)."""

    reward_transform: str = "symlog"
    shaping_coef: float = 0.0
    aim_coef: float = 0.0
    success_bonus: float = 0.0
    fail_penalty: float = 0.0
    step_penalty: float = 0.0

    def __post_init__(self) -> None:
        if self.reward_transform not in REWARD_TRANSFORMS:
            raise UsageError(f"unknown reward transform {self.reward_transform!r} "
                             f"(known: {', '.join(REWARD_TRANSFORMS)})")


def make_train_env(task: str, config: Config | None, shaping: Shaping, *,
                   critic_state: bool = False, **env_kwargs: Any) -> gym.Env:
    """The task's env with the trainer's reward (and with ``critic_state``, the privileged
    state in its info: ``CriticState``); a module-level function, so it pickles for
    ``AsyncVectorEnv`` (one PyBullet client per worker)."""
    env: gym.Env = JetbotEnv(task, config, **env_kwargs)
    if critic_state:
        env = CriticState(env)
    env = RecordEpisodeStatistics(env)
    if shaping.reward_transform == "symlog":
        env = TransformReward(env, symlog)
    if shaping.shaping_coef:
        env = PotentialShaping(env, "distance", shaping.shaping_coef)
    if shaping.aim_coef:
        env = PotentialShaping(env, "aim_error", shaping.aim_coef)
    if shaping.success_bonus or shaping.fail_penalty:
        env = OutcomeBonus(env, shaping.success_bonus, shaping.fail_penalty)
    if shaping.step_penalty:
        env = StepPenalty(env, shaping.step_penalty)
    return env


def normalize_rewards(envs: gym.vector.VectorEnv, gamma: float, clip: float
                      ) -> tuple[gym.vector.VectorEnv, Any]:
    """Divide by the running std of the discounted return, then clip to +-``clip``.
    Returns the wrapped env and the ``NormalizeReward`` wrapper (its ``return_rms`` is the
    state a checkpoint keeps)."""
    from gymnasium.wrappers.vector import ClipReward, NormalizeReward

    normalizer = NormalizeReward(envs, gamma=gamma)
    return ClipReward(normalizer, -clip, clip), normalizer
