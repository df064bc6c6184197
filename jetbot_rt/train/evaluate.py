"""Deterministic evaluation of an ONNX policy: the runtime's ``OnnxPolicy`` (same frame
preparation, action output ``mu``) driving the env at the policy's input size. Episode
``i`` starts from the scene drawn with seed ``seed + i``, so results do not depend on how
episodes are spread over workers.

Blind baselines and seam ablations (``ablate``), on the same episodes:

- ``blank``: the policy sees a constant mid-grey image instead of the camera frame;
- ``bgr``: frames prepared in the other colour order than the model declares (the runtime's
  ``[policy] color_order`` override: the seam of a BGR camera fed to an RGB-trained model);
- ``pixel-range``: frames prepared in another pixel range than the model declares (0..1 for a
  0..255 model, else 0..255);
- ``constant-forward``: no network at all, ``mu = [1, 1]`` at every step.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jetbot_rt.config.sections import Config
from jetbot_rt.errors import UsageError
from jetbot_rt.runtime.policy import OnnxPolicy, resolve_policy_path, trained_calibrated
from jetbot_rt.tasks import BUILTIN, load_task
from jetbot_rt.train.env import JetbotEnv, action_pipeline_of, calibrated_robot
from jetbot_rt.train.hyperparams import OptionError
from jetbot_rt.train.out_dir import own_directory
from jetbot_rt.train.vec_env import workers_ignore_the_working_directory
from jetbot_rt.train.versions import versions
from jetbot_rt.train.video import EpisodeRecording, timed

ABLATIONS = ("blank", "bgr", "pixel-range", "constant-forward")
BLANK_LEVEL = 128


class ConstantPolicy:
    """``mu`` = ``value`` whatever the frame; no max_speed of its own, so the task's applies.
    ``spec`` and ``path`` are the replaced policy's (the env renders at its input size)."""

    max_speed = None
    metadata: dict[str, str] = {}  # noqa: RUF012 - read only

    def __init__(self, replaced: OnnxPolicy, value: tuple[float, float] = (1.0, 1.0)) -> None:
        self.value = np.array(value, dtype=np.float64)
        self.spec = replaced.spec
        self.path = replaced.path

    def infer(self, image: np.ndarray) -> np.ndarray:
        return self.value.copy()


class BlankPolicy:
    """The wrapped policy, fed a constant mid-grey frame of the camera's size."""

    def __init__(self, policy: OnnxPolicy) -> None:
        self.policy = policy
        self.max_speed = policy.max_speed
        self.spec, self.path, self.metadata = policy.spec, policy.path, policy.metadata

    def infer(self, image: np.ndarray) -> np.ndarray:
        return self.policy.infer(np.full_like(image, BLANK_LEVEL))


def _ablated_config(config: Config, policy: OnnxPolicy, ablate: str | None) -> Config:
    spec = policy.spec
    if ablate == "bgr":
        swapped = "BGR" if spec.color_order == "RGB" else "RGB"
        return replace(config, policy=replace(config.policy, color_order=swapped))
    if ablate == "pixel-range":
        other = "0-1" if spec.pixel_range == "0-255" else "0-255"
        return replace(config, policy=replace(config.policy, pixel_range=other))
    return config


def load_policy(path: str | Path, config: Config, single_thread: bool = True,
                ablate: str | None = None) -> Any:
    """``OnnxPolicy.load`` (all of its checks); with ``single_thread`` onnxruntime uses one
    thread, so parallel eval workers do not fight over cores. ``ablate``: see the module."""
    if ablate is not None and ablate not in ABLATIONS:
        raise OptionError("ablate", f"must be one of {', '.join(ABLATIONS)}, got {ablate!r}")
    threads = 1 if single_thread else None
    policy = OnnxPolicy.load(path, config.policy, threads=threads)
    if ablate == "constant-forward":
        return ConstantPolicy(policy)
    if ablate == "blank":
        return BlankPolicy(policy)
    if ablate in ("bgr", "pixel-range"):
        return OnnxPolicy.load(path, _ablated_config(config, policy, ablate).policy,
                               threads=threads)
    return policy


def run_episode(env: JetbotEnv, policy: Any, seed: int | None,
                options: dict[str, Any] | None = None,
                video_dir: str | None = None) -> dict[str, Any]:
    """One episode with ``mu`` as the action; returns return, final distance, success.
    With ``video_dir``, the episode is recorded there (``jetbot_rt.train.video``)."""
    video = EpisodeRecording.of(video_dir, env, policy, seed) if video_dir else None
    obs, info = env.reset(seed=seed, options=options)
    total = 0.0
    steps = 0
    truncated = terminated = False
    while not (truncated or terminated):
        seen = obs
        mu, infer_ms = timed(policy.infer, seen)
        (obs, reward, terminated, truncated, info), step_ms = timed(env.step, mu)
        total += reward
        steps += 1
        if video is not None:
            video.step(seen, mu, info, infer_ms, step_ms)
    result = {
        "seed": seed,
        "return": total,
        "steps": steps,
        "final_distance": float(info["distance"]) if "distance" in info else None,
        "block_shift": float(info["block_shift"]) if "block_shift" in info else None,
        "success": bool(info["is_success"]),
    }
    if video is not None:
        video.close(result)
    return result


_WORKER: dict[str, Any] = {}
"""One policy and env per worker process, kept between its episodes."""


def _run_one(job: tuple[str, str, Config, int, str | None, str | None]) -> dict:
    path, task, config, seed, ablate, video_dir = job
    key = (path, task, repr(config), ablate)
    if _WORKER.get("key") != key:
        if "env" in _WORKER:
            _WORKER["env"].close()
        if multiprocessing.parent_process() is not None:
            cv2.setNumThreads(1)  # one core per pool worker (sampler.PolicySampler says why)
        policy = load_policy(path, config, ablate=ablate)
        env = JetbotEnv(task, config, model_max_speed=policy.max_speed,
                        image_size=(policy.spec.width, policy.spec.height))
        _WORKER.update(key=key, policy=policy, env=env)
    return run_episode(_WORKER["env"], _WORKER["policy"], seed, video_dir=video_dir)


def success_rule(spec: Any) -> str | None:
    """What ``outcome`` counts as a success, in words, for a goal task (``success_distance``
    and, where the task sets them, ``stop_speed`` and ``max_block_shift``); None for others."""
    if spec.success_distance is None:
        return None
    parts = [f"final distance < {spec.success_distance:g} m"]
    if getattr(spec, "stop_speed", None) is not None:
        parts.append(f"slower than {spec.stop_speed:g} m/s")
    if getattr(spec, "max_block_shift", None) is not None:
        parts.append(f"the block pushed less than {spec.max_block_shift:g} m")
    return " and ".join(parts)


def _stat(function: Any, values: list[float | None]) -> float | None:
    """``function`` of ``values``, None for a task that reports no such value."""
    return None if any(v is None for v in values) else float(function(values))


def evaluate(
    policy_path: str | Path | None = None,
    *,
    task: str = "forward",
    episodes: int = 100,
    seed: int = 10_000,
    num_workers: int = 1,
    config: Config | None = None,
    ablate: str | None = None,
    progress: bool = False,
    video_dir: str | None = None,
) -> dict[str, Any]:
    """Evaluate ``policy_path`` (default: the bundled policy of ``task``) over ``episodes``
    episodes; record each in ``video_dir/episode-<seed>/`` if given."""
    from tqdm import tqdm

    if episodes <= 0:
        raise OptionError("episodes", f"must be > 0, got {episodes}")
    if num_workers <= 0:
        raise OptionError("num_workers", f"must be > 0, got {num_workers}")
    spec = load_task(task)
    if policy_path is None and task not in BUILTIN:
        raise UsageError(f"no bundled policy for task {task!r}; pass --policy FILE.onnx")
    config = config or Config()
    if video_dir is not None:  # refused before any episode runs, as a run directory is
        os.close(own_directory(video_dir, "--video directory"))
    path = resolve_policy_path(policy_path, task)
    policy = load_policy(path, config, ablate=ablate)  # fail early, here, on a bad file
    seeds = [seed + i for i in range(episodes)]
    workers = min(num_workers, episodes)
    start = time.perf_counter()
    bar = tqdm(total=episodes, disable=not progress, unit="episode", dynamic_ncols=True)
    try:
        if workers == 1:
            results = []
            try:
                for one in seeds:
                    results.append(_run_one((str(path), task, config, one, ablate, video_dir)))
                    bar.update(1)
            finally:
                if "env" in _WORKER:
                    _WORKER.pop("env").close()
                _WORKER.clear()
        else:
            jobs = [(str(path), task, config, one, ablate, video_dir) for one in seeds]
            # For the pool's whole life: it starts a new worker in place of one that died.
            with workers_ignore_the_working_directory(), \
                    multiprocessing.get_context("spawn").Pool(workers) as pool:
                results = []
                for result in pool.imap_unordered(_run_one, jobs):
                    results.append(result)
                    bar.update(1)
            results.sort(key=lambda r: r["seed"])
    finally:
        bar.close()
    wall = time.perf_counter() - start
    return {
        "policy": "constant [1, 1]" if ablate == "constant-forward" else str(path),
        "task": task,
        "episodes": episodes,
        "success_rate": float(np.mean([r["success"] for r in results])),
        "mean_return": float(np.mean([r["return"] for r in results])),
        "mean_final_distance": _stat(np.mean, [r["final_distance"] for r in results]),
        "max_final_distance": _stat(np.max, [r["final_distance"] for r in results]),
        "success_distance": spec.success_distance,
        "success_rule": success_rule(spec),
        "versions": versions(),
        "episode_steps": spec.episode_steps,
        "seed": seed,
        "max_speed": action_pipeline_of(
            config, policy.max_speed if policy.max_speed is not None else spec.max_speed
        ).max_speed,
        "ablate": ablate,
        # a calibrated robot's lift, and whether the policy was trained for one: a
        # calibrated policy measured without the lift is measured on an uncalibrated robot
        "deadband_lift": (config.randomize.deadband_lift if calibrated_robot(config, spec)
                          else None),
        "calibrated_policy": trained_calibrated(policy.metadata),  # an ablation's too
        "successes": [r["seed"] for r in results if r["success"]],
        "wall_s": round(wall, 2),
        "env_steps_per_s": round(sum(r["steps"] for r in results) / wall, 1),
    }
