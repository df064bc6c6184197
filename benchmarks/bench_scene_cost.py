"""How much an env step costs in one randomized scene against another (issue 21): for each
task, ``--scenes`` episodes (seeds 500+), each stepped ``--steps`` times with policy-like
commands (``bench_sim.actions``) in one process; each scene's median step time.

Why: PPO's rollout waits for its slowest worker, and a worker's scene (its clutter, lights,
looks) stays the same for a whole episode, several rollouts long. If scenes differ in cost, a
rollout of N workers runs at the pace of the dearest of N scenes while the simulator alone
(``bench_sim``) averages over them. The "gated" figure estimates that pace: the mean of the
scene costs over the mean, over 2000 draws, of the dearest of ``--workers`` scenes drawn from
the measured ones (a model: it takes each worker's segment to cost its scene's median).

    python benchmarks/bench_scene_cost.py [--tasks forward seek] [--scenes 40] [--tag TAG]

Writes scene_cost[-TAG].json and .md to --out.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from bench_sim import PATHS, actions, machine
from versions import write_results

from jetbot_rt.train.env import JetbotEnv


def scene_costs(task: str, scenes: int, steps: int) -> list[float]:
    """Each scene's median step time (ms)."""
    env = JetbotEnv(task, image_size=(PATHS["train"]["size"],) * 2)
    commands = actions(np.random.default_rng(0), steps).astype(np.float32)
    costs = []
    try:
        for scene in range(scenes):
            env.reset(seed=500 + scene)
            times = []
            for command in commands:
                start = time.perf_counter()
                _, _, terminated, truncated, _ = env.step(command)
                times.append(time.perf_counter() - start)
                if terminated or truncated:
                    env.reset()  # the rest of the steps in the next scene's place: rare
            costs.append(round(1e3 * statistics.median(times), 3))
    finally:
        env.close()
    return costs


def gated_share(costs: list[float], workers: int, draws: int = 2000) -> float:
    """The mean scene cost over the mean cost of the dearest of ``workers`` scenes."""
    rng = np.random.default_rng(0)
    dearest = rng.choice(np.array(costs), size=(draws, workers)).max(axis=1)
    return round(float(np.mean(costs) / dearest.mean()), 3)


def markdown(result: dict) -> str:
    m = result["machine"]
    lines = ["# Step cost by scene", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}; 1-min load "
             f"average {m['loadavg_1min_at_start']} at start. Command: `{result['command']}`.",
             "", f"{result['scenes']} scenes a task (seeds 500+), {result['steps']} steps each; "
             "each scene's median step time (ms). Gated: the mean scene cost over the expected "
             f"cost of the dearest of {result['workers']} scenes (a rollout's pace when each "
             "worker's segment costs its scene's median).", "",
             "| task | min | 25 % | median | 75 % | max | max / min | gated |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in result["tasks"]:
        q = np.percentile(row["costs_ms"], [0, 25, 50, 75, 100])
        lines.append(f"| {row['task']} | " + " | ".join(f"{v:.2f}" for v in q)
                     + f" | {q[4] / q[0]:.2f} | {row['gated_share']:.1%} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=["forward", "seek"])
    parser.add_argument("--scenes", type=int, default=40)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--workers", type=int, default=16)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    parser.add_argument("--tag", default="")
    args = parser.parse_args()
    result: dict = {"machine": {**machine(), "loadavg_1min_at_start": round(os.getloadavg()[0], 2)},
                    "scenes": args.scenes, "steps": args.steps, "workers": args.workers,
                    "command": "python benchmarks/bench_scene_cost.py " + " ".join(sys.argv[1:]),
                    "tasks": []}
    for task in args.tasks:
        costs = scene_costs(task, args.scenes, args.steps)
        result["tasks"].append({"task": task, "costs_ms": costs,
                                "gated_share": gated_share(costs, args.workers)})
        print(task, result["tasks"][-1]["gated_share"], flush=True)
    name = f"scene_cost-{args.tag}" if args.tag else "scene_cost"
    write_results(args.out, name, result, markdown(result))


if __name__ == "__main__":
    main()
