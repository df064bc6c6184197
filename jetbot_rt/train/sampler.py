"""PPO's rollout inside the env worker processes: each worker steps its env with its own copy
of the policy for a whole rollout and sends it back at once, instead of a round trip to the
learner for every step.

Why: with one env per core, a round trip per step serialises the machine -- the workers wait
while the learner runs the network on two frames and merges their results, the learner waits
while the workers step -- and the learner's share (network call, pipes, bookkeeping) cost
about as much as an env step (docs/TRAINING.md, "Speed"). Sampling in the workers costs one
small forward pass per step in each worker and nothing in between.

PPO's semantics are kept: the weights are the learner's at the start of the rollout, every env
steps ``num_steps`` times, an episode that ends is reset in the same step (SAME_STEP, as the
vector env does), and a time-limit truncation carries the value of its final observation for
bootstrapping. The rewards go back unnormalised; ``normalize_segment`` replays the vector
env's ``NormalizeReward`` + ``ClipReward`` over them in step order, on the same state.
The sampling noise comes from a numpy generator seeded by (run seed, update, env index).

With PPO's asymmetric critic (``--critic state``) the env's info carries the privileged state
(``wrappers.CriticState``): the worker sends each step's state back beside its frame (and a
truncated episode's final state), and the learner computes the values from them with its
critic; the worker's copy is the actor alone.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable
from typing import Any

import cv2
import gymnasium as gym
import numpy as np
import torch

from jetbot_rt.train.hyperparams import ModelConfig
from jetbot_rt.train.model import LOG_SQRT_2PI, ActorCritic
from jetbot_rt.train.shared_steps import Share, SharedSteps
from jetbot_rt.train.wrappers import CRITIC_STATE


class PolicySampler(gym.Wrapper):
    """The env of one worker, with ``collect``: a rollout segment with a copy of the policy.
    ``reset`` is the env's (the vector env resets every worker at the start of training).

    The copy runs on onnxruntime, as on the robot: the network exported once with its weights
    as inputs (``export.weights_as_inputs``), fed the learner's weights at each rollout. On one
    frame it costs a quarter of torch's forward pass (0.15 vs 0.55 ms a step, this machine);
    its outputs match torch's to ~1e-6."""

    def __init__(self, env: gym.Env, model: ModelConfig, index: int) -> None:
        import onnxruntime as ort

        from jetbot_rt.train.export import weights_as_inputs

        super().__init__(env)
        self.model_config = model
        self.index = index
        self._obs: np.ndarray | None = None
        self._state: np.ndarray | None = None
        """The privileged state of ``_obs`` (``info["critic_state"]``), when the env has one."""
        self._shared: SharedSteps | None = None
        # Built with the env, as the worker starts (~0.3 s of CPU), not in the first rollout.
        if multiprocessing.parent_process() is not None:
            torch.set_num_threads(1)  # one core per worker
            # and OpenCV's (the lens's remap, the looks' filters), whose default is a pool of
            # one thread per core in every worker: three trainings of 5-6 workers each read a
            # 1-min load average of 115 on 16 cores without this, 13-19 with it
            cv2.setNumThreads(1)
        options = ort.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = 1
        options.log_severity_level = 3  # no warning that the weights are inputs
        self._session = ort.InferenceSession(weights_as_inputs(ActorCritic(model)), options,
                                             providers=["CPUExecutionProvider"])
        self._weights = {i.name for i in self._session.get_overridable_initializers()}

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._obs = obs
        self._state = info.get(CRITIC_STATE)
        return obs, info

    def _policy(self, weights: dict[str, np.ndarray]) -> Callable[[np.ndarray], list]:
        feeds = {name: np.asarray(w) for name, w in weights.items()}
        if set(feeds) != self._weights:  # a weight not fed would silently keep its first value
            raise ValueError(f"weights {sorted(feeds)} do not match the network's "
                             f"{sorted(self._weights)}")
        session = self._session
        return lambda frame: session.run(None, {"obs": frame.astype(np.float32), **feeds})

    def collect(self, weights: dict[str, np.ndarray], num_steps: int,
                seed: tuple[int, int], share: Share | None = None) -> dict[str, Any]:
        """``num_steps`` steps with the policy of ``weights`` (arrays named as in the
        network's ``state_dict``); ``seed``: (run seed, update). With ``share`` (PPO's
        ``--balance``): at most ``num_steps``, ending once this worker has taken
        ``share.min_steps`` and the workers together ``share.total`` (``shared_steps``).

        Returns arrays over the steps -- ``obs`` (the frame the action was chosen on),
        ``actions``, ``logprobs``, ``values``, ``rewards`` (the wrapped env's, before
        normalisation), ``terminated``, ``truncated``, ``final_values`` (value of the final
        frame where an episode was truncated, else 0) -- plus ``next_obs`` (the frame the
        next rollout starts from) and ``episodes``: (step, return, distance, success) of each
        episode that ended. When the env's info has the privileged critic state, also
        ``states`` (of each step's frame), ``final_states`` (of the final frame where an
        episode was truncated, else 0) and ``next_state``; ``values`` and ``final_values``
        are then the image head's or 0 (the learner's critic replaces them)."""
        if self._obs is None:
            raise RuntimeError("collect before reset")
        policy = self._policy(weights)
        rng = np.random.default_rng([seed[0], seed[1], self.index])
        obs = np.empty((num_steps, *self._obs.shape), dtype=self._obs.dtype)
        actions = np.empty((num_steps, 2), dtype=np.float32)
        logprobs, values, final_values = (np.zeros(num_steps, dtype=np.float32)
                                          for _ in range(3))
        rewards = np.empty(num_steps, dtype=np.float64)
        terminated, truncated = (np.zeros(num_steps, dtype=np.bool_) for _ in range(2))
        episodes: list[tuple[int, float, float, float]] = []
        state = self._state
        if state is not None:
            states = np.empty((num_steps, *state.shape), dtype=np.float32)
            final_states = np.zeros_like(states)
        counts = None if share is None else self._counts(share)[share.bank]
        length = num_steps
        for t in range(num_steps):
            obs[t] = self._obs
            if state is not None:
                states[t] = state
            mu, log_std, value = policy(obs[t:t + 1])
            std = np.exp(log_std[0])
            actions[t] = mu[0] + std * rng.standard_normal(2, dtype=np.float32)
            logprobs[t] = np.sum(-((actions[t] - mu[0]) ** 2) / (2 * std**2) - np.log(std)
                                 - LOG_SQRT_2PI)
            values[t] = value[0, 0]
            next_obs, rewards[t], terminated[t], truncated[t], info = self.env.step(actions[t])
            if terminated[t] or truncated[t]:
                if truncated[t] and not terminated[t]:
                    if state is not None:
                        final_states[t] = info[CRITIC_STATE]
                    else:
                        final_values[t] = policy(next_obs[None])[2][0, 0]
                episodes.append((t, float(info["episode"]["r"]),
                                 float(info.get("distance", np.nan)),  # a task may have none
                                 float(info["is_success"])))
                next_obs, info = self.env.reset()
            self._obs = next_obs
            if state is not None:
                state = self._state = info[CRITIC_STATE]
            if counts is not None:
                counts[self.index] = t + 1
                if t + 1 >= share.min_steps and counts.sum() >= share.total:
                    length = t + 1
                    break
        segment = {"obs": obs, "actions": actions, "logprobs": logprobs, "values": values,
                   "rewards": rewards, "terminated": terminated, "truncated": truncated,
                   "final_values": final_values}
        if state is not None:
            segment.update(states=states, final_states=final_states)
        segment = {key: steps[:length] for key, steps in segment.items()}
        segment.update(next_obs=np.array(self._obs), episodes=episodes)
        if state is not None:
            segment["next_state"] = np.array(state)
        return segment

    def close(self) -> None:
        if self._shared is not None:
            self._shared.close()
            self._shared = None
        super().close()

    def _counts(self, share: Share) -> np.ndarray:
        """The balanced rollouts' step counters (``[bank, worker]``), attached once."""
        if self._shared is None or self._shared.name != share.name:
            if self._shared is not None:
                self._shared.close()
            self._shared = SharedSteps.attach(share.name, share.workers)
        return self._shared.counts


def stack_segments(segments: tuple[dict[str, Any], ...]) -> dict[str, Any]:
    """The envs' segments as ``[num_steps, num_envs, ...]`` arrays (``next_obs`` and
    ``next_state``: ``[num_envs, ...]``); ``episodes`` as (step, env, return, distance,
    success) in the order a vector env would have reported them; ``lengths``, each env's
    steps. Segments of different lengths (``--balance``) are padded with zeros to the
    longest."""
    per_env = [k for k in ("next_obs", "next_state") if k in segments[0]]
    keys = [k for k in segments[0] if k not in (*per_env, "episodes")]
    lengths = np.array([len(s["rewards"]) for s in segments])
    longest = int(lengths.max())

    def padded(steps: np.ndarray) -> np.ndarray:
        if len(steps) == longest:
            return steps
        pad = np.zeros((longest - len(steps), *steps.shape[1:]), dtype=steps.dtype)
        return np.concatenate([steps, pad])

    stacked = {k: np.stack([padded(s[k]) for s in segments], axis=1) for k in keys}
    stacked["lengths"] = lengths
    stacked.update({k: np.stack([s[k] for s in segments]) for k in per_env})
    stacked["episodes"] = sorted((t, i, *rest) for i, s in enumerate(segments)
                                 for t, *rest in s["episodes"])
    return stacked


def normalize_segment(normalizer: Any, clip: float, rewards: np.ndarray,
                      terminated: np.ndarray, truncated: np.ndarray,
                      lengths: np.ndarray | None = None) -> np.ndarray:
    """``[num_steps, num_envs]`` rewards as ``ClipReward(NormalizeReward(envs), -clip, clip)``
    returns them step by step with SAME_STEP autoreset (Gymnasium 1.x), updating the same
    state (``normalizer.accumulated_reward``, ``normalizer.return_rms``). With ``lengths``
    (each env's steps, the rest padding) step t is of the envs that have it."""
    out = np.zeros_like(rewards)
    returns = normalizer.accumulated_reward
    for t in range(len(rewards)):
        envs = slice(None) if lengths is None else np.flatnonzero(t < lengths)
        returns[envs] = returns[envs] * normalizer.gamma * (1 - terminated[t, envs]) + \
            rewards[t, envs]
        if normalizer.update_running_mean:  # the returns as stored (the wrapper's dtype)
            normalizer.return_rms.update(returns[envs])
        returns[envs] = np.where(terminated[t, envs] | truncated[t, envs], 0, returns[envs])
        scaled = rewards[t, envs] / np.sqrt(normalizer.return_rms.var + normalizer.epsilon)
        out[t, envs] = np.clip(scaled, -clip, clip)
    return out


__all__ = ["PolicySampler", "normalize_segment", "stack_segments"]
