"""A task's privileged teacher (``Task.expert``), for DAgger: reads the simulator's state from
the env's ``info``, never the image. ``Expert`` is the goal tasks' one (seek's), whose
parameters the DAgger options tune (``hyperparams.DAggerArgs``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from jetbot_rt.errors import UsageError
from jetbot_rt.tasks import Expert as ExpertProtocol
from jetbot_rt.tasks import Task, load_task
from jetbot_rt.tasks.goal_expert import GoalExpert as Expert

__all__ = ["Expert", "evaluate_expert", "task_expert"]


def task_expert(task: str | Task, settings: dict[str, Any] | None = None) -> ExpertProtocol:
    """``task``'s expert, its dataclass fields named in ``settings`` replaced (the DAgger
    options named like them); ``UsageError`` when the task has none."""
    loaded = load_task(task)
    expert = loaded.expert()
    if expert is None:
        raise UsageError(f"task {loaded.short_name()!r} has no expert for DAgger (its "
                         "Task.expert() returns None); train it with --algo ppo")
    if settings and dataclasses.is_dataclass(expert):
        known = {f.name for f in dataclasses.fields(expert)}
        expert = dataclasses.replace(expert, **{k: v for k, v in settings.items() if k in known})
    return expert


EXPERT_FRAME = (8, 8)
"""The frame size of an env only an expert drives: it reads the env's info, never pixels, so
the smallest render (half a step's time against 56x56 through the fisheye and the looks)."""


def evaluate_expert(episodes: int = 100, seed: int = 10_000, task: str = "seek") -> float:
    """The expert's own success rate on the evaluation's episodes (seed + i, the task's
    randomization on), acting on the state each frame shows (DAgger's ``--expert-sees
    frame``): what the student can at best reach."""
    from jetbot_rt.train.dagger_sampler import FrameState
    from jetbot_rt.train.env import JetbotEnv

    env, expert, successes = JetbotEnv(task, image_size=EXPERT_FRAME), task_expert(task), 0
    try:
        for i in range(episodes):
            _, info = env.reset(seed=seed + i)
            seen = FrameState(info, env.period)
            done = False
            while not done:
                _, _, terminated, truncated, info = env.step(expert.label(seen.info))
                seen.push(info)
                done = terminated or truncated
            successes += bool(info["is_success"])
    finally:
        env.close()
    return successes / episodes


if __name__ == "__main__":  # python -m jetbot_rt.train.expert [EPISODES] [TASK]
    import sys

    count = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    name = sys.argv[2] if len(sys.argv) > 2 else "seek"
    print(f"expert success {evaluate_expert(count, task=name):.0%} over {count} {name} episodes")
