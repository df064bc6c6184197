"""What the fisheye lens costs per step, against the pinhole at the training size and the
224x224 path of the performance budget (training path >= 4x its env steps/s), in one run:
(a) the runtime's per-tick cost (step 1/30 s + render), (b) ``JetbotEnv.step`` steps/s of the
seek task (randomized, as it trains), one process after another.

    python benchmarks/bench_lens.py [--env-steps 900] [--rounds 3] [--out benchmarks/results]

Writes lens.json and lens.md to --out. The paths alternate round by round so that a load
that comes and goes falls on all of them alike; medians over the rounds.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from bench_sim import actions, env_steps_per_s, machine, stats_ms
from versions import write_results

from jetbot_rt.config.sections import Config
from jetbot_rt.sim.config import SimConfig
from jetbot_rt.sim.lens import lens_warp
from jetbot_rt.sim.world import JetbotWorld
from jetbot_rt.train.env import POLICY_IMAGE_SIZE, JetbotEnv

TICK = 1 / 30
SIZE = POLICY_IMAGE_SIZE
PATHS = {
    "224": {"size": 224, "sim": {"physics_hz": 240.0},
            "label": "224x224 pinhole, physics 240 Hz (the budget's reference path)"},
    "pinhole": {"size": SIZE, "sim": {},
                "label": f"{SIZE}x{SIZE} pinhole, 120 Hz (the training path today)"},
    "fisheye": {"size": SIZE, "sim": {"lens": "fisheye"},
                "label": f"{SIZE}x{SIZE} fisheye (lens = \"fisheye\", datasheet lens), 120 Hz"},
}


def bench_tick(path: dict, ticks: int) -> dict[str, object]:
    world = JetbotWorld(SimConfig(**path["sim"]), image_size=(path["size"], path["size"]))
    duties = 0.1 * actions(np.random.default_rng(0), ticks)
    step_s, render_s = [], []
    for i in range(ticks):
        world.set_duty(*duties[i])
        t0 = time.perf_counter()
        world.step(TICK)
        t1 = time.perf_counter()
        world.render()
        render_s.append(time.perf_counter() - t1)
        step_s.append(t1 - t0)
    world.close()
    return {"step": stats_ms(step_s), "render": stats_ms(render_s)}


def bench_env(path: dict, steps: int) -> float:
    config = Config()
    for key, value in path["sim"].items():
        setattr(config.sim, key, value)
    env = JetbotEnv("seek", config, image_size=(path["size"], path["size"]))
    return env_steps_per_s(env, steps, seed=0)


def markdown(result: dict) -> str:
    m = result["machine"]
    env = result["env_steps_per_s_median"]
    lines = [
        "# The lens's cost", "",
        f"`{result['command']}`, {result['date']}.", "",
        f"Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}; 1-min load average "
        f"{m['loadavg_1min_at_start']} at start, {m['loadavg_1min_at_end']} at the end "
        "(other jobs' load included: the ratios, measured in the same run, are what to read).",
        "", f"Per tick, {result['ticks']} ticks per round, median ms (of the rounds' medians):",
        "", "| path | step | render (fisheye: pinhole render + remap) | env steps/s (seek, "
        "1 process) | vs 224x224 |", "| --- | --- | --- | --- | --- |",
    ]
    for key, path in PATHS.items():
        t = result["tick"][key]
        lines.append(f"| {path['label']} | {t['step_ms']} | {t['render_ms']} | {env[key]} | "
                     f"x{round(env[key] / env['224'], 2)} |")
    lines += ["", f"The fisheye against the pinhole at {SIZE}x{SIZE}: env steps/s "
              f"x{result['fisheye_vs_pinhole']}; the budget (>= 4x the 224x224 path): "
              f"x{round(env['fisheye'] / env['224'], 2)}.", "",
              f"Render size under the fisheye: {result['fisheye_render_size']} for the "
              f"{SIZE}x{SIZE} frame."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ticks", type=int, default=300)
    parser.add_argument("--env-steps", type=int, default=900)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()
    result: dict = {
        "command": "python " + " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]),
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine(), "ticks": args.ticks,
        "paths": {k: {"size": p["size"], "sim": p["sim"]} for k, p in PATHS.items()},
    }
    ticks: dict[str, list] = {k: [] for k in PATHS}
    rates: dict[str, list] = {k: [] for k in PATHS}
    for r in range(args.rounds):
        for key, path in PATHS.items():
            ticks[key].append(bench_tick(path, args.ticks))
            rates[key].append(bench_env(path, args.env_steps))
            print(r, key, round(rates[key][-1], 1), ticks[key][-1]["render"], flush=True)
    result["tick"] = {k: {
        "step_ms": round(float(np.median([t["step"]["median_ms"] for t in v])), 3),
        "render_ms": round(float(np.median([t["render"]["median_ms"] for t in v])), 3),
    } for k, v in ticks.items()}
    result["env_steps_per_s"] = {k: [round(x, 1) for x in v] for k, v in rates.items()}
    env = {k: round(float(np.median(v)), 1) for k, v in rates.items()}
    result["env_steps_per_s_median"] = env
    result["fisheye_vs_pinhole"] = round(env["fisheye"] / env["pinhole"], 2)
    warp = lens_warp(SimConfig(lens="fisheye"), (SIZE, SIZE))
    result["fisheye_render_size"] = "x".join(map(str, warp.render_size)) if warp else "-"
    result["machine"]["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    write_results(args.out, "lens", result, markdown(result))


if __name__ == "__main__":
    main()
