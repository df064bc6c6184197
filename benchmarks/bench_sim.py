"""Measure the PyBullet simulation at the training size against the 224x224 path it replaced,
in the same run: (a) the runtime's per-tick cost (step 1/30 s + render), (b) Gymnasium env
steps per second (``JetbotEnv.step``: action pipeline, physics, render, info) with 1, 2, ...
processes stepping side by side.

    python benchmarks/bench_sim.py [--processes 1 2] [--env-steps 900] [--out benchmarks/results]

Writes sim.json and sim.md to --out (``--tag`` names them sim-TAG.* instead).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from versions import cpu_model, write_results

from jetbot_rt.config.sections import Config
from jetbot_rt.sim.config import SimConfig
from jetbot_rt.sim.world import JetbotWorld
from jetbot_rt.train.env import POLICY_IMAGE_SIZE, JetbotEnv

TICK = 1 / 30
EPISODE_TICKS = 450  # the forward task's 15 s episodes
PATHS = {
    "224": {"size": 224, "physics_hz": 240.0,
            "label": "224x224, physics 240 Hz (the path before issue 10)"},
    "train": {"size": POLICY_IMAGE_SIZE, "physics_hz": SimConfig().physics_hz,
              "label": f"{POLICY_IMAGE_SIZE}x{POLICY_IMAGE_SIZE}, physics "
                       f"{SimConfig().physics_hz:g} Hz (training size, defaults)"},
}


def actions(rng: np.random.Generator, n: int) -> np.ndarray:
    """Policy-like wheel commands: mostly forward, changing every step."""
    return np.clip(0.7 + 0.5 * rng.standard_normal((n, 2)), -1.0, 1.0)


def stats_ms(seconds: list[float]) -> dict[str, float]:
    a = np.array(seconds) * 1e3
    return {"median_ms": round(float(np.median(a)), 3),
            "p99_ms": round(float(np.percentile(a, 99)), 3), "mean_ms": round(float(a.mean()), 3)}


def bench_tick(path: dict, ticks: int) -> dict[str, object]:
    """The runtime's sim backend per tick: world.step(1/30) then render()."""
    world = JetbotWorld(SimConfig(physics_hz=path["physics_hz"]),
                        image_size=(path["size"], path["size"]))
    duties = 0.1 * actions(np.random.default_rng(0), ticks)
    step_s, render_s, cpu_s = [], [], []
    for i in range(ticks):
        if i % EPISODE_TICKS == 0:
            world.reset()
        world.set_duty(*duties[i])
        c0, t0 = time.thread_time(), time.perf_counter()
        world.step(TICK)
        t1 = time.perf_counter()
        world.render()
        t2 = time.perf_counter()
        cpu_s.append(time.thread_time() - c0)
        step_s.append(t1 - t0)
        render_s.append(t2 - t1)
    world.close()
    return {"ticks": ticks, "tick_cpu": stats_ms(cpu_s), "step": stats_ms(step_s),
            "render": stats_ms(render_s)}


def env_steps_per_s(env: JetbotEnv, steps: int, seed: int,
                    before: Callable[[], object] = lambda: None) -> float:
    """Env steps per second of ``steps`` seeded random commands, after 20 warm-up steps outside
    the timed part (``before`` runs just before the clock starts); closes ``env``."""
    commands = actions(np.random.default_rng(seed), steps)
    env.reset(seed=seed)
    for i in range(20):
        env.step(commands[i])
    env.reset(seed=seed)
    before()
    t0 = time.perf_counter()
    for i in range(steps):
        _, _, terminated, truncated, _ = env.step(commands[i])
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - t0
    env.close()
    return steps / elapsed


def env_worker(path: dict, steps: int, seed: int, ready: mp.Barrier, out: mp.Queue) -> None:
    config = Config()
    config.sim.physics_hz = path["physics_hz"]
    env = JetbotEnv(path.get("task", "forward"), config, image_size=(path["size"], path["size"]))
    out.put(env_steps_per_s(env, steps, seed, ready.wait))


def bench_env(path: dict, processes: int, steps: int) -> dict[str, object]:
    ctx = mp.get_context("spawn")
    ready, out = ctx.Barrier(processes), ctx.Queue()
    workers = [ctx.Process(target=env_worker, args=(path, steps, seed, ready, out))
               for seed in range(processes)]
    for w in workers:
        w.start()
    rates = [out.get(timeout=1200) for _ in workers]
    for w in workers:
        w.join()
    return {"processes": processes, "steps_per_process": steps,
            "steps_per_s_per_process": sorted(round(r, 1) for r in rates),
            "steps_per_s_total": round(sum(rates), 1)}


def machine() -> dict[str, object]:
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "python": platform.python_version(),
            "loadavg_1min_at_start": round(os.getloadavg()[0], 2)}


def markdown(result: dict) -> str:
    m = result["machine"]
    lines = [
        "# Simulation benchmark", "",
        f"Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}; 1-min load average "
        f"{m['loadavg_1min_at_start']} at start, {m['loadavg_1min_at_end']} at the end "
        "(other jobs' load included).", "",
        "Per tick (`step(1/30)` + `render()`), "
        f"{result['ticks']} ticks, median / p99 ms:", "",
        "| path | tick CPU | step | render |", "| --- | --- | --- | --- |",
    ]
    for key, path in PATHS.items():
        t = result["tick"][key]
        lines.append(f"| {path['label']} | " + " | ".join(
            f"{t[n]['median_ms']} / {t[n]['p99_ms']}" for n in ("tick_cpu", "step", "render"))
            + " |")
    lines += [
        "", f"Gymnasium env steps/s (`JetbotEnv.step`, reset every {EPISODE_TICKS} steps), "
        "processes stepping side by side, the two paths in the same run:", "",
        "| processes | 224x224 path: total (per process) | training size: total (per process) "
        "| ratio |", "| --- | --- | --- | --- |",
    ]
    for row in result["env"]:
        base, new = row["224"], row["train"]
        lines.append(
            f"| {row['processes']} | {base['steps_per_s_total']} "
            f"({', '.join(map(str, base['steps_per_s_per_process']))}) | "
            f"{new['steps_per_s_total']} ({', '.join(map(str, new['steps_per_s_per_process']))})"
            f" | x{row['ratio']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ticks", type=int, default=450)
    parser.add_argument("--env-steps", type=int, default=900)
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    parser.add_argument("--tag", default="", help="write sim-TAG.json / sim-TAG.md")
    args = parser.parse_args()

    result: dict = {"machine": machine(), "ticks": args.ticks, "paths": PATHS}
    result["tick"] = {key: bench_tick(path, args.ticks) for key, path in PATHS.items()}
    result["env"] = []
    for n in args.processes:
        row = {"processes": n, **{k: bench_env(p, n, args.env_steps) for k, p in PATHS.items()}}
        row["ratio"] = round(row["train"]["steps_per_s_total"] / row["224"]["steps_per_s_total"], 2)
        result["env"].append(row)
        print(row, flush=True)
    result["machine"]["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    name = f"sim-{args.tag}" if args.tag else "sim"
    write_results(args.out, name, result, markdown(result))


if __name__ == "__main__":
    main()
