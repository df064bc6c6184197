"""Replays the episodes ``jetbot-train eval`` reported as misses (the seeds of its ``--json``
output absent from ``successes``) with the evaluation's own environment and ablation, and
sorts each with a task's own rule: what ``avoid_misses.py`` and ``seek_misses.py`` share."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from eval_report import evaluation_arguments, read_evaluation

from jetbot_rt.config.sections import load_config
from jetbot_rt.train.env import JetbotEnv, calibrated_robot
from jetbot_rt.train.evaluate import load_policy


@dataclass(frozen=True)
class Episode:
    """What a replayed episode did, besides its last step's info."""

    start: np.ndarray
    """The robot's xy at the reset."""
    farthest: float
    """m; the farthest the robot got from ``start`` at any step."""
    mean_command: np.ndarray
    """The policy's mean output (left, right) over the episode."""
    last_command: np.ndarray
    """The policy's output (left, right) at the last step: where a robot stopped short, is
    it commanding a stop, or a crawl that a dead-band swallows?"""


Sort = Callable[[JetbotEnv, dict, Episode], tuple[str, str]]
"""(the env, the last step's info, the episode) -> (the kind, a line of detail)."""


def replay(env: JetbotEnv, policy: Any, seed: int) -> tuple[dict, Episode]:
    obs, info = env.reset(seed=seed)
    start = np.asarray(info["pose"][:2], dtype=float)
    farthest, commands, done = 0.0, [], False
    while not done:
        command = policy.infer(obs)
        commands.append(np.asarray(command, dtype=float).reshape(-1))
        obs, _, terminated, truncated, info = env.step(command)
        farthest = max(farthest, float(np.linalg.norm(np.asarray(info["pose"][:2]) - start)))
        done = terminated or truncated
    return info, Episode(start, farthest, np.mean(commands, axis=0), commands[-1])


@dataclass
class Replay:
    """An evaluation to replay: its seeds and successes, the policy and the env it ran."""

    seeds: range
    successes: set[int]
    policy: Any
    env: JetbotEnv


def open_replay(task: str, doc: str) -> Replay:
    """The command line every replaying script takes (``--policy``, ``--eval``,
    ``--episodes``, ``--config``), read: the evaluation's environment and ablation rebuilt.
    The caller closes ``env``."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--policy", required=True)
    evaluation_arguments(parser, "an eval --json output of this policy")
    args = parser.parse_args()
    report, seeds, successes = read_evaluation(args.eval, args.episodes)
    config = load_config(args.config)
    lift = config.randomize.deadband_lift if calibrated_robot(config, task) else None
    if "deadband_lift" in report and report["deadband_lift"] != lift:
        parser.error(f"{args.eval} ran with deadband_lift {report['deadband_lift']}, this "
                     f"config gives {lift}: pass the --config the evaluation ran with")
    policy = load_policy(args.policy, config, ablate=report.get("ablate"))
    env = JetbotEnv(task, config, model_max_speed=policy.max_speed,
                    image_size=(policy.spec.width, policy.spec.height))
    return Replay(seeds, successes, policy, env)


def main(task: str, doc: str, sort: Sort) -> None:
    run = open_replay(task, doc)
    counts: dict[str, int] = {}
    try:
        for seed in sorted(set(run.seeds) - run.successes):
            info, episode = replay(run.env, run.policy, seed)
            found, detail = sort(run.env, info, episode)
            counts[found] = counts.get(found, 0) + 1
            print(f"{seed}: {found} ({detail})", flush=True)
    finally:
        run.env.close()
    print(", ".join(f"{n} {k}" for k, n in sorted(counts.items())))
