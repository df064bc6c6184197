"""Deterministic evaluation of an ONNX policy: the runtime's ``OnnxPolicy`` (same frame
preparation, action output ``mu``) driving the env. Episode ``i`` starts from the pose drawn
with seed ``seed + i``, so results do not depend on how episodes are spread over workers."""

from __future__ import annotations

import multiprocessing
import time
from pathlib import Path
from typing import Any

import numpy as np

from jetbot_rt.config import Config
from jetbot_rt.errors import UsageError
from jetbot_rt.policy import OnnxPolicy, resolve_policy_path
from jetbot_rt.train.env import JetbotEnv, action_pipeline_of, get_task
from jetbot_rt.train.video import EpisodeRecording, timed


def load_policy(path: str | Path, config: Config, single_thread: bool = True) -> OnnxPolicy:
    """``OnnxPolicy.load`` (all of its checks); with ``single_thread`` onnxruntime uses one
    thread, so parallel eval workers do not fight over cores."""
    return OnnxPolicy.load(path, config.policy, threads=1 if single_thread else None)


def run_episode(env: JetbotEnv, policy: OnnxPolicy, seed: int | None,
                options: dict[str, Any] | None = None,
                video_dir: str | None = None) -> dict[str, Any]:
    """One episode with ``mu`` as the action; returns return, final distance, success.
    With ``video_dir``, the episode is recorded there (``jetbot_rt.train.video``)."""
    video = EpisodeRecording.of(video_dir, env, policy, seed) if video_dir else None
    obs, info = env.reset(seed=seed, options=options)
    total = 0.0
    truncated = terminated = False
    while not (truncated or terminated):
        seen = obs
        mu, infer_ms = timed(policy.infer, seen)
        (obs, reward, terminated, truncated, info), step_ms = timed(env.step, mu)
        total += reward
        if video is not None:
            video.step(seen, mu, info, infer_ms, step_ms)
    result = {
        "seed": seed,
        "return": total,
        "final_distance": float(info["distance"]),
        "success": bool(info["is_success"]),
    }
    if video is not None:
        video.close(result)
    return result


def _run_episodes(policy_path: str, task: str, config: Config, seeds: list[int],
                  video_dir: str | None = None) -> list[dict]:
    policy = load_policy(policy_path, config)
    env = JetbotEnv(task, config, model_max_speed=policy.max_speed,
                    image_size=(policy.spec.width, policy.spec.height))
    try:
        return [run_episode(env, policy, seed, video_dir=video_dir) for seed in seeds]
    finally:
        env.close()


def evaluate(
    policy_path: str | Path | None = None,
    *,
    task: str = "forward",
    episodes: int = 100,
    seed: int = 10_000,
    num_workers: int = 1,
    config: Config | None = None,
    video_dir: str | None = None,
) -> dict[str, Any]:
    """Evaluate ``policy_path`` (default: the bundled policy) over ``episodes`` episodes;
    record each in ``video_dir/episode-<seed>/`` if given."""
    if episodes <= 0:
        raise UsageError(f"--episodes must be > 0, got {episodes}")
    if num_workers <= 0:
        raise UsageError(f"--num-envs must be > 0, got {num_workers}")
    spec = get_task(task)
    config = config or Config()
    path = resolve_policy_path(policy_path)
    policy = load_policy(path, config)  # fail early, in this process, on a bad file
    seeds = [seed + i for i in range(episodes)]
    workers = min(num_workers, episodes)
    start = time.perf_counter()
    if workers == 1:
        results = _run_episodes(str(path), task, config, seeds, video_dir)
    else:
        chunks = [seeds[i::workers] for i in range(workers)]
        with multiprocessing.get_context("spawn").Pool(workers) as pool:
            parts = pool.starmap(
                _run_episodes, [(str(path), task, config, chunk, video_dir) for chunk in chunks]
            )
        results = sorted((r for part in parts for r in part), key=lambda r: r["seed"])
    wall = time.perf_counter() - start
    return {
        "policy": str(path),
        "task": task,
        "episodes": episodes,
        "success_rate": float(np.mean([r["success"] for r in results])),
        "mean_return": float(np.mean([r["return"] for r in results])),
        "mean_final_distance": float(np.mean([r["final_distance"] for r in results])),
        "max_final_distance": float(np.max([r["final_distance"] for r in results])),
        "success_distance": spec.success_distance,
        "episode_steps": spec.episode_steps,
        "seed": seed,
        "max_speed": action_pipeline_of(config, policy.max_speed).max_speed,
        "wall_s": round(wall, 2),
        "env_steps_per_s": round(episodes * spec.episode_steps / wall, 1),
    }
