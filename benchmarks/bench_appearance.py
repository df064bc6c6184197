"""What the appearance families cost an episode: env reset and step wall times at the training
size (56x56, the seek task), today's room against the families, in the same run.

Cases: "default" (seek's own randomization, no families), "families" (``[randomize]
appearance = true``: a new floor and wall texture, clutter, light and camera look every
episode), "worst" (families on, and every episode a rug with three lamps, a window, shadows,
six pieces of clutter, textured walls and the whole camera look). Per case: ``resets`` resets
of new seeds, then ``steps`` steps of a fixed action after each. Timed in this process's CPU
time by default (on a shared, loaded machine the wall time measures the queue for a core). Writes
benchmarks/results/appearance.json and .md. Run:

  .venv/bin/python benchmarks/bench_appearance.py [--resets 40] [--steps 60]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from versions import stamp

from jetbot_rt.config.sections import from_dict
from jetbot_rt.train.env import JetbotEnv

OUT = Path(__file__).resolve().parent / "results"
WORST = {"floor_families": ["rug"], "wall_textures": ["wallpaper"], "clutter": [6, 6],
         "lamps": [3, 3], "window_light": [1.0, 1.0], "shadows": 1.0, "skirting": 1.0,
         "motion_blur": [0.02, 0.02], "gain_noise": [0.03, 0.03], "vignetting": [0.5, 0.5]}
CPU = True
# "default" says appearance = false: the families are on by default since 2026-11-26
CASES = {"default": {"appearance": False}, "families": {"appearance": True},
         "worst": {"appearance": True, **WORST}}


def measure(name: str, resets: int, steps: int) -> dict[str, float]:
    env = JetbotEnv("seek", from_dict({"randomize": CASES[name]}))
    # CPU time of this process: on a loaded machine the wall time is mostly waiting for a core
    clock = time.process_time if CPU else time.perf_counter
    reset_ms, step_ms = [], []
    action = np.array([0.6, 0.5])
    try:
        env.reset(seed=0)  # imports and first-use costs out of the figures
        for seed in range(1, resets + 1):
            t = clock()
            env.reset(seed=seed)
            reset_ms.append(1e3 * (clock() - t))
            t = clock()
            for _ in range(steps):
                env.step(action)
            step_ms.append(1e3 * (clock() - t) / steps)  # per step, averaged over the episode
    finally:
        env.close()
    return {"reset_ms_median": statistics.median(reset_ms),
            "step_ms_median": statistics.median(step_ms),
            "episode_ms_at_300_steps": statistics.median(reset_ms)
            + 300 * statistics.median(step_ms)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resets", type=int, default=40)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--wall", action="store_true",
                        help="wall-clock times (default: this process's CPU time)")
    args = parser.parse_args()
    global CPU
    CPU = not args.wall
    load_before = os.getloadavg()
    # interleaved, twice, so a change in the machine's load falls on every case alike
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in CASES}
    for _ in range(2):
        for name in CASES:
            runs[name].append(measure(name, args.resets // 2, args.steps))
    results = {name: {key: statistics.mean(r[key] for r in rs) for key in rs[0]}
               for name, rs in runs.items()}
    base = results["default"]
    for r in results.values():
        r["reset_ratio"] = r["reset_ms_median"] / base["reset_ms_median"]
        r["step_ratio"] = r["step_ms_median"] / base["step_ms_median"]
        r["episode_ratio"] = r["episode_ms_at_300_steps"] / base["episode_ms_at_300_steps"]
    meta = {"command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
            "machine": f"{platform.node()}, {os.cpu_count()} cores, {platform.processor()}",
            "date": f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC",
            "load_average": [round(x, 1) for x in (*load_before, *os.getloadavg())],
            "resets": args.resets, "steps_per_reset": args.steps,
            "clock": "process CPU time" if CPU else "wall",
            "lens": from_dict({}).sim.lens}
    OUT.mkdir(exist_ok=True)
    (OUT / "appearance.json").write_text(json.dumps(stamp({**meta, "results": results}), indent=2))
    lines = [
        f"# What the appearance families cost (seek, 56x56, {meta['lens']} lens)", "",
        f"Command: `.venv/bin/python benchmarks/{meta['command']}`  ",
        f"Machine: {meta['machine']}; load average before / after "
        f"{meta['load_average'][:3]} / {meta['load_average'][3:]}  ",
        f"Date: {meta['date']}; {args.resets} resets per case, {args.steps} steps after each "
        f"(a step's time: the mean over those), cases interleaved in two rounds; clock: "
        f"{meta['clock']}", "",
        "| case | reset, median | step, median | episode of 300 steps | ratio: reset / step / "
        "episode |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, r in results.items():
        lines.append(f"| {name} | {r['reset_ms_median']:.1f} ms | {r['step_ms_median']:.2f} ms | "
                     f"{r['episode_ms_at_300_steps']:.0f} ms | {r['reset_ratio']:.2f} / "
                     f"{r['step_ratio']:.2f} / {r['episode_ratio']:.2f} |")
    (OUT / "appearance.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
