"""Measure the PyBullet simulation: (a) the runtime's per-tick cost (step 1/30 s + render
224x224), (b) env-style steps per second per process, 1 and 2 processes in parallel.

    python benchmarks/bench_sim.py [--ticks 600] [--env-steps 900] [--out benchmarks/results]

Writes sim.json and sim.md to --out.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import time
from pathlib import Path

import numpy as np

from jetbot_rt.config import SimConfig
from jetbot_rt.sim.world import JetbotWorld

TICK = 1 / 30
EPISODE_TICKS = 450  # 15 s episodes, as a trainer might use


def duty_schedule(rng: np.random.Generator, n: int) -> np.ndarray:
    """Policy-like duties: within +-0.1 (the default max_speed), changing every tick."""
    return np.clip(0.07 + 0.05 * rng.standard_normal((n, 2)), -0.1, 0.1)


def stats_ms(seconds: list[float]) -> dict[str, float]:
    a = np.array(seconds) * 1e3
    return {
        "median_ms": round(float(np.median(a)), 3),
        "p99_ms": round(float(np.percentile(a, 99)), 3),
        "mean_ms": round(float(a.mean()), 3),
        "max_ms": round(float(a.max()), 3),
    }


def bench_tick(ticks: int) -> dict[str, object]:
    """The runtime's sim backend per tick: world.step(1/30) then render()."""
    world = JetbotWorld(SimConfig())
    duties = duty_schedule(np.random.default_rng(0), ticks)
    step_s, render_s, tick_s, cpu_s = [], [], [], []
    for i in range(ticks):
        if i % EPISODE_TICKS == 0:
            world.reset()
        world.set_duty(*duties[i])
        c0 = time.thread_time()
        t0 = time.perf_counter()
        world.step(TICK)
        t1 = time.perf_counter()
        world.render()
        t2 = time.perf_counter()
        cpu_s.append(time.thread_time() - c0)
        step_s.append(t1 - t0)
        render_s.append(t2 - t1)
        tick_s.append(t2 - t0)
    reset_s = []
    for _ in range(20):
        t0 = time.perf_counter()
        world.reset()
        reset_s.append(time.perf_counter() - t0)
    world.close()
    return {
        "ticks": ticks,
        "tick": stats_ms(tick_s),
        "tick_cpu": stats_ms(cpu_s),
        "step": stats_ms(step_s),
        "render": stats_ms(render_s),
        "reset": stats_ms(reset_s),
    }


def env_worker(steps: int, seed: int, start: mp.Event, out: mp.Queue) -> None:
    """What a Gymnasium env step costs: duty, step, render, distance; reset per episode."""
    world = JetbotWorld(SimConfig())
    duties = duty_schedule(np.random.default_rng(seed), steps)
    for _ in range(30):  # warm-up outside the timed part
        world.step(TICK)
        world.render()
    world.reset()
    start.wait()
    t0 = time.perf_counter()
    for i in range(steps):
        if i and i % EPISODE_TICKS == 0:
            world.reset()
        world.set_duty(*duties[i])
        world.step(TICK)
        world.render()
        world.distance_to_block()
    elapsed = time.perf_counter() - t0
    world.close()
    out.put(steps / elapsed)


def bench_env(processes: int, steps: int) -> dict[str, object]:
    ctx = mp.get_context("spawn")
    start, out = ctx.Event(), ctx.Queue()
    workers = [
        ctx.Process(target=env_worker, args=(steps, seed, start, out)) for seed in range(processes)
    ]
    for w in workers:
        w.start()
    time.sleep(3.0)  # let every worker build its world and warm up
    start.set()
    rates = [out.get(timeout=600) for _ in workers]
    for w in workers:
        w.join()
    return {
        "processes": processes,
        "steps_per_process": steps,
        "steps_per_s_per_process": [round(r, 1) for r in rates],
        "steps_per_s_total": round(sum(rates), 1),
    }


def machine() -> dict[str, object]:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import pybullet

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "pybullet_api": pybullet.getAPIVersion(),
        "loadavg_1min_at_start": round(os.getloadavg()[0], 2),
    }


def markdown(result: dict) -> str:
    t = result["tick"]
    one, two = result["env_1_process"], result["env_2_processes"]
    rows = [
        "| measure | median | p99 |",
        "| --- | --- | --- |",
    ]
    for name in ("tick", "tick_cpu", "step", "render", "reset"):
        s = t[name]
        rows.append(f"| {name} (ms) | {s['median_ms']} | {s['p99_ms']} |")
    return "\n".join(
        [
            "# Simulation benchmark",
            "",
            f"Machine: {result['machine']['cpu']}, {result['machine']['cores']} cores, "
            f"1-min load average {result['machine']['loadavg_1min_at_start']} at start "
            "(shared with other jobs while measured).",
            "",
            f"Tick = `step(1/30)` (8 physics sub-steps at 240 Hz) + `render()` 224x224 "
            f"(TinyRenderer), {t['ticks']} ticks:",
            "",
            *rows,
            "",
            "`tick_cpu` is the CPU time the tick's thread used: what a tick costs without "
            "waiting for a core.",
            "",
            "Env-style steps (duty, step, render, distance; reset every "
            f"{EPISODE_TICKS} steps):",
            "",
            "| processes | steps/s per process | steps/s total |",
            "| --- | --- | --- |",
            f"| 1 | {one['steps_per_s_per_process'][0]} | {one['steps_per_s_total']} |",
            f"| 2 | {', '.join(map(str, two['steps_per_s_per_process']))} "
            f"| {two['steps_per_s_total']} |",
            "",
            f"Scaling 1 -> 2 processes: x{result['scaling_1_to_2']}",
            "",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ticks", type=int, default=600)
    parser.add_argument("--env-steps", type=int, default=900)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()

    result: dict[str, object] = {"machine": machine()}
    result["tick"] = bench_tick(args.ticks)
    result["env_1_process"] = bench_env(1, args.env_steps)
    result["env_2_processes"] = bench_env(2, args.env_steps)
    result["scaling_1_to_2"] = round(
        result["env_2_processes"]["steps_per_s_total"]
        / result["env_1_process"]["steps_per_s_total"],
        2,
    )
    result["machine"]["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "sim.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / "sim.md").write_text(markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
