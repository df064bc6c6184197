"""DAgger's rollouts inside the env worker processes: each worker drives whole episodes with
its onnxruntime copy of the student (or the expert, with noise, for a ``beta`` share of the
episodes), labels every frame with the expert's action and sends the finished episodes back
at once, instead of a round trip to the learner for every step.

Why: the learner's share of a step -- the student's forward pass on the frames, the expert on
the infos, the pipes -- cost more than the env step itself (a DAgger iteration of 3 000 steps
collected in 9-13 s on two idle cores, 2.4 ms of env step per core). The copy is the one PPO's
sampler runs (``sampler.PolicySampler``); the labels are the same function of the state.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np

from jetbot_rt.tasks import Expert
from jetbot_rt.train.hyperparams import ModelConfig
from jetbot_rt.train.sampler import PolicySampler


class FrameState:
    """The expert's view of an episode as its frames show it: the info of the tick the
    camera's latency ago (``sim_params["camera_latency"]`` of the reset's info, in whole
    control periods, rounded; the frame itself may show a moment between two ticks, within
    half a period). Before that many ticks have passed, the reset's info: the world stood
    still in its reset state before the episode, as the first frames show it.

    Why: a label on the true state *now* asks the student to see through the camera's
    latency, which one frame cannot; labels of the state the frame shows are a function of
    the frame, and the expert driving on them is the controller the student can become (seek
    with 150 ms motor plus 100 ms camera latency: 99 of 100 episodes; docs/TRAINING.md)."""

    def __init__(self, reset_info: dict[str, Any], period: float | None) -> None:
        """``period``: the control period (s); None: no lag, the state at the frame's
        delivery (``--expert-sees now``)."""
        latency = float(reset_info.get("sim_params", {}).get("camera_latency", 0.0))
        lag = 0 if period is None else round(latency / period)
        self._infos = deque([reset_info], maxlen=lag + 1)

    def push(self, info: dict[str, Any]) -> None:
        self._infos.append(info)

    @property
    def info(self) -> dict[str, Any]:
        return self._infos[0]


class LabelSampler(PolicySampler):
    """The env of one DAgger worker, with ``collect_labelled``."""

    def __init__(self, env: gym.Env, model: ModelConfig, index: int) -> None:
        super().__init__(env, model, index)
        self._info: dict[str, Any] = {}

    def collect_labelled(self, weights: dict[str, np.ndarray], min_steps: int,
                         seed: tuple[int, int], beta: float, noise: float,
                         expert: Expert, expert_sees: str = "frame") -> dict[str, Any]:
        """Whole episodes until at least ``min_steps`` frames; ``seed``: (run seed,
        iteration), which seed the first scene (then the env's own draws) and the draws of
        who drives and of the noise. Each episode is driven by the expert (action noise
        ``noise``) with probability ``beta``, else by the student's ``mu``. ``expert_sees``:
        "frame", the expert labels and drives on the state the frame shows
        (``FrameState``); "now", on the state at the frame's delivery.

        Returns ``frames`` (uint8, every frame an action was chosen on), ``labels`` (the
        expert's action on each), ``symmetric`` (the expert's ``symmetric`` on each; all
        false for an expert without it) and ``outcomes``: (driven by the expert, success)
        per episode."""
        policy = self._policy(weights)
        rng = np.random.default_rng([seed[0], seed[1], self.index])
        obs, info = self.env.reset(seed=seed[0] * 100_000 + seed[1] * 1000 + self.index)
        frames: list[np.ndarray] = []
        labels: list[np.ndarray] = []
        symmetric: list[bool] = []
        mirrors = getattr(expert, "symmetric", None)
        outcomes: list[tuple[bool, bool]] = []
        period = float(self.env.unwrapped.period) if expert_sees == "frame" else None
        while len(frames) < min_steps:
            by_expert = bool(rng.random() < beta)
            seen = FrameState(info, period)
            done = False
            while not done:
                label = expert.label(seen.info)
                if by_expert:
                    noisy = label + rng.normal(0.0, noise, 2).astype(np.float32)
                    action = np.clip(noisy, -1.0, 1.0)
                else:
                    action = np.clip(policy(obs[None])[0][0], -1.0, 1.0)
                frames.append(obs)
                labels.append(label)
                symmetric.append(mirrors is not None and bool(mirrors(seen.info)))
                obs, _, terminated, truncated, info = self.env.step(action)
                seen.push(info)
                done = terminated or truncated
            outcomes.append((by_expert, bool(info["is_success"])))
            obs, info = self.env.reset()
        return {"frames": np.stack(frames), "labels": np.stack(labels).astype(np.float32),
                "symmetric": np.array(symmetric, dtype=bool), "outcomes": outcomes}
