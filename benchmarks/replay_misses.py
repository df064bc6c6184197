"""Replays the episodes ``jetbot-train eval`` reported as misses (the seeds of its ``--json``
output absent from ``successes``) with the evaluation's own environment, and sorts each with
a task's own rule: what ``avoid_misses.py`` and ``seek_misses.py`` share."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

import numpy as np

from jetbot_rt.config.safe_file import read_json
from jetbot_rt.config.sections import load_config
from jetbot_rt.train.env import JetbotEnv
from jetbot_rt.train.evaluate import load_policy

Sort = Callable[[JetbotEnv, dict, np.ndarray], tuple[str, str]]
"""(the env, the last step's info, the robot's start xy) -> (the kind, a line of detail)."""


def main(task: str, doc: str, sort: Sort) -> None:
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--policy", required=True)
    parser.add_argument("--eval", required=True, help="an eval --json output of this policy")
    parser.add_argument("--episodes", type=int, default=100, help="the evaluation's count")
    parser.add_argument("--config", default=None)
    args = parser.parse_args()
    report: Any = read_json(args.eval, "evaluation", 1 << 20)
    report = report.get("heldout", report)  # a device script's {"heldout": ..., "blank": ...}
    first = report["seed"]
    misses = sorted(set(range(first, first + args.episodes)) - set(report["successes"]))
    config = load_config(args.config)
    policy = load_policy(args.policy, config)
    env = JetbotEnv(task, config, model_max_speed=policy.max_speed,
                    image_size=(policy.spec.width, policy.spec.height))
    counts: dict[str, int] = {}
    try:
        for seed in misses:
            obs, info = env.reset(seed=seed)
            start = np.asarray(info["pose"][:2], dtype=float)
            done = False
            while not done:
                obs, _, terminated, truncated, info = env.step(policy.infer(obs))
                done = terminated or truncated
            found, detail = sort(env, info, start)
            counts[found] = counts.get(found, 0) + 1
            print(f"{seed}: {found} ({detail})", flush=True)
    finally:
        env.close()
    print(", ".join(f"{n} {k}" for k, n in sorted(counts.items())))
