"""What ``[actions] deadband`` (the lift of every duty that is not zero by the motor's
dead-band) is worth to a policy: the same randomized episodes with no lift, and with the lift
set to each episode's drawn dead-band plus an offset (0: a perfect calibration; +-0.05: one
that over- or under-states it by 0.05 of duty). The policies were trained without it.

    python benchmarks/bench_deadband_lift.py --task avoid --episodes 400 \\
        --offsets none 0 0.05 -0.05 --out benchmarks/results/deadband_lift/avoid.json

Writes the JSON (command, date, machine, versions, per arm: success rate, the successful
seeds and success by quartile of the drawn dead-band) and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import multiprocessing
from pathlib import Path

import numpy as np
from bench_sim import machine
from versions import run_record, stamp

from jetbot_rt.config.sections import load_config
from jetbot_rt.train.env import JetbotEnv
from jetbot_rt.train.evaluate import load_policy, resolve_policy_path

QUARTILES = (0.0, 0.075, 0.15, 0.225, 0.3)
"""Of the default ``[randomize] deadband`` range, 0 .. 0.3 of duty."""


def run(job: tuple[str, str, str, list[int]]) -> list[tuple[int, float, bool]]:
    """(seed, drawn dead-band, success) of each episode of ``seeds`` with one arm's lift."""
    task, policy_path, offset, seeds = job
    config = load_config(None)
    policy = load_policy(policy_path, config)
    env = JetbotEnv(task, config, model_max_speed=policy.max_speed,
                    image_size=(policy.spec.width, policy.spec.height))
    plain = env.pipeline
    out = []
    try:
        for seed in seeds:
            obs, info = env.reset(seed=seed)
            drawn = float(env.world.sim.deadband)
            lift = 0.0 if offset == "none" else max(drawn + float(offset), 0.0)
            env.pipeline = dataclasses.replace(plain, deadband=lift)
            done = False
            while not done:
                obs, _, terminated, truncated, info = env.step(policy.infer(obs))
                done = terminated or truncated
            out.append((seed, drawn, bool(info["is_success"])))
    finally:
        env.close()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", required=True)
    parser.add_argument("--policy", default=None, help="default: the task's bundled policy")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=10_000)
    parser.add_argument("--offsets", nargs="+", default=["none", "0"],
                        help='"none" (no lift) or the offset added to the drawn dead-band')
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    policy = str(resolve_policy_path(args.policy, args.task))
    seeds = list(range(args.seed, args.seed + args.episodes))
    chunks = [seeds[i::args.workers] for i in range(args.workers)]
    jobs = [(args.task, policy, offset, chunk) for offset in args.offsets for chunk in chunks]
    result = {**run_record(), "machine": machine(), "task": args.task, "policy": policy,
              "episodes": args.episodes, "seed": args.seed, "arms": {}}
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        done = pool.map(run, jobs)
    print(f"| lift | success ({args.episodes} episodes) | by drawn dead-band "
          f"{', '.join(f'{a:g}-{b:g}' for a, b in itertools.pairwise(QUARTILES))} |\n"
          "| --- | --- | --- |")
    for k, offset in enumerate(args.offsets):
        episodes = sorted(e for part in done[k * args.workers:(k + 1) * args.workers]
                          for e in part)
        drawn = np.array([d for _, d, _ in episodes])
        ok = np.array([s for _, _, s in episodes])
        which = np.clip(np.searchsorted(QUARTILES, drawn, side="right") - 1, 0, 3)
        bins = [f"{int(ok[which == i].sum())}/{int((which == i).sum())}" for i in range(4)]
        name = "none" if offset == "none" else f"drawn {float(offset):+g}"
        result["arms"][name] = {"success_rate": float(ok.mean()), "by_deadband": bins,
                                "successes": [s for s, _, good in episodes if good]}
        print(f"| {name} | {100 * ok.mean():.1f} % | {', '.join(bins)} |")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(stamp(result), indent=1) + "\n")


if __name__ == "__main__":
    main()
