"""``jetbot-train eval --video DIR``: each evaluated episode recorded the way ``jetbot-rt run
--record`` records a run (docs/RECORDING.md), into ``DIR/episode-<seed>/``, so that
``jetbot-rt report`` and ``jetbot-rt replay`` look at sim evaluations and real runs alike.

A step is a tick: the frame the policy received, its ``mu``, the duties the env applied, the
pose after the step; ``t`` is simulated time. Nothing is dropped (the writer may make the
evaluation wait: nothing else does).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from jetbot_rt.config.sections import Config
from jetbot_rt.recording.recorder import Recorder, sha256_of
from jetbot_rt.runtime.loop import TickResult


class EpisodeRecording:
    def __init__(self, video_dir: str | Path, seed: int | None, policy: Any, policy_path: Path,
                 task: str, config: Config, frame_size: tuple[int, int],
                 max_speed: float) -> None:
        self.period = config.loop.period
        self.now = 0.0
        self.steps = 0
        describe = getattr(policy, "describe", None)
        meta = {
            "source": "jetbot-train eval",
            "backend": "sim",
            "task": task,
            "seed": seed,
            "policy": {**(describe() if describe else {}), "path": str(policy_path),
                       "sha256": sha256_of(policy_path),
                       "metadata": getattr(policy, "metadata", {})},
            "max_speed": max_speed,
            "config": dataclasses.asdict(config),
        }
        self.recorder = Recorder(Path(video_dir) / f"episode-{seed}", meta, frame_size,
                                 config.loop.rate_hz, blocking=True, t0=0.0,
                                 clock=lambda: self.now)

    @classmethod
    def of(cls, video_dir: str | Path, env: Any, policy: Any, seed: int | None,
           ) -> EpisodeRecording:
        """The recording of one episode of ``env`` driven by ``policy`` (an ``OnnxPolicy``)."""
        height, width = env.observation_space.shape[:2]
        return cls(video_dir, seed, policy, Path(policy.path), env.task.name, env.config,
                   (width, height), env.pipeline.max_speed)

    def step(self, image: np.ndarray, mu: np.ndarray, info: dict[str, Any],
             infer_ms: float, step_ms: float) -> None:
        """One step: ``image`` the policy saw, ``mu`` it gave, ``info`` the env's after it."""
        step, self.steps = self.steps, self.steps + 1
        t = step * self.period
        self.now = t + self.period
        duty = info["duty"]
        self.recorder.observe(TickResult(
            tick=step + 1, t_start=t, deadline=t, image=image, frame_index=step,
            frame_age_ms=0.0, mu=[float(mu[0]), float(mu[1])],
            cmd=(float(duty[0]), float(duty[1])), infer_ms=infer_ms,
            tick_ms=infer_ms + step_ms, write_ms=0.0, advance_ms=step_ms, overruns=0,
            extra={"pose": [float(v) for v in info["pose"]], "sim_time": self.now,
                   "task": task_measures(info)},
        ))

    def close(self, result: dict[str, Any]) -> None:
        self.recorder.close({"reason": "episode end", **result}, timeout=None)


ENV_KEYS = ("pose", "duty", "sim_time")


def task_measures(info: dict[str, Any]) -> dict[str, float]:
    """The task's finite scalar outcome values of a step's ``info`` (seek's ``distance``,
    follow's ``offset`` and ``progress``, ...): a task names its own, and many have no
    distance. A tick records them under ``task``, apart from its own fields."""
    measures = {}
    for key, value in info.items():
        if key in ENV_KEYS or not isinstance(key, str) \
                or isinstance(value, (bool, np.bool_)) \
                or not isinstance(value, (int, float, np.integer, np.floating)):
            continue
        try:
            number = float(value)
        except OverflowError:  # an int past float's range
            continue
        if math.isfinite(number):
            measures[key] = number
    return measures


def timed(function: Any, *args: Any) -> tuple[Any, float]:
    """``function(*args)`` and its wall time in ms."""
    start = time.perf_counter()
    value = function(*args)
    return value, (time.perf_counter() - start) * 1e3
