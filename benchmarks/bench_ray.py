"""Ray env workers versus the trainer's AsyncVectorEnv, same machine, same run.

    python benchmarks/bench_ray.py        # this machine: 2 workers, ~1.5 min idle on 2 cores
    python benchmarks/bench_ray.py --workers 1 2 4 8 16 --no-ppo --tag h100   # a big host

Two figures, each with its AsyncVectorEnv baseline measured in the same run, alternating
(baseline, Ray, baseline, Ray, ...) so that a change of the machine's load hits both:
- env steps/s of the vector env alone (seeded random actions) on the same number of cores:
  AsyncVectorEnv with ``workers`` processes of one env each (the trainer's default, one per
  core) versus RayVectorEnv with ``workers`` actors of ``envs-per-worker`` envs each (the
  actors' per-step round trip is shared by their envs);
- PPO end to end (``train``, the training loop's steps/s, start-up excluded) with the same
  PPO arguments, ``workers x envs-per-worker`` envs: one process per env for the baseline.
Ray runs on this machine (``ray.init`` with every core); its start-up is reported apart.
Writes benchmarks/results/ray[-TAG].{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np
from versions import stamp

RESULTS = Path(__file__).resolve().parent / "results"


def load() -> float:
    return os.getloadavg()[0]


def env_rate(kind: str, num_envs: int, workers: int, steps: int) -> float:
    if kind == "async":
        num_envs = workers
    from gymnasium.vector import AsyncVectorEnv, AutoresetMode

    from jetbot_rt.config.sections import Config
    from jetbot_rt.train.env import make_task_env
    from jetbot_rt.train.ray_workers import RayVectorEnv

    fns = [partial(make_task_env, "forward", Config()) for _ in range(num_envs)]
    if kind == "ray":
        envs = RayVectorEnv(fns, workers=workers)
    else:
        envs = AsyncVectorEnv(fns, context="spawn", autoreset_mode=AutoresetMode.SAME_STEP,
                              shared_memory=True)
    rng = np.random.default_rng(0)
    try:
        envs.reset(seed=list(range(num_envs)))
        for _ in range(10):  # warm-up
            envs.step(rng.uniform(-1, 1, (num_envs, 2)).astype(np.float32))
        start = time.perf_counter()
        for _ in range(steps):
            envs.step(rng.uniform(-1, 1, (num_envs, 2)).astype(np.float32))
        return num_envs * steps / (time.perf_counter() - start)
    finally:
        envs.close()


def ppo_rate(kind: str, num_envs: int, workers: int, updates: int, num_steps: int) -> float:
    from jetbot_rt.train.hyperparams import PPOArgs
    from jetbot_rt.train.ppo import train
    with tempfile.TemporaryDirectory() as out:
        args = PPOArgs(num_envs=num_envs, num_steps=num_steps,
                       total_timesteps=num_envs * num_steps * updates, device="cpu",
                       out=out, progress=False, checkpoint_every=10**6,
                       ray="local" if kind == "ray" else None,
                       workers=workers if kind == "ray" else None,
                       sample_in_workers=False)  # both the per-step loop: Ray's own overhead
        return float(train(args)["steps_per_s"])


def compare(measure, repeats: int) -> dict:
    rates: dict[str, list[float]] = {"async": [], "ray": []}
    for _ in range(repeats):
        for kind in ("async", "ray"):
            rates[kind].append(round(measure(kind), 1))
    base, ray = statistics.median(rates["async"]), statistics.median(rates["ray"])
    return {"async": rates["async"], "ray": rates["ray"], "async_median": round(base, 1),
            "ray_median": round(ray, 1), "ray_vs_async": round(ray / base, 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, nargs="+", default=[2])
    parser.add_argument("--envs-per-worker", type=int, default=4)
    parser.add_argument("--env-steps", type=int, default=200, help="vector steps per measure")
    parser.add_argument("--ppo-updates", type=int, default=2)
    parser.add_argument("--ppo-steps", type=int, default=32, help="PPO steps per env per update")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--no-ppo", action="store_true", help="env steps/s only")
    parser.add_argument("--tag", help="results file suffix (e.g. the machine)")
    args = parser.parse_args()

    import ray

    load_start = load()
    began = start = time.perf_counter()
    ray.init(address="local", num_cpus=os.cpu_count(), include_dashboard=False,
             log_to_driver=False)
    ray_start_s = round(time.perf_counter() - start, 2)
    rows = []
    try:
        for workers in args.workers:
            num_envs = workers * args.envs_per_worker
            row = {"workers": workers, "num_envs": num_envs,
                   "env": compare(partial(env_rate, num_envs=num_envs, workers=workers,
                                          steps=args.env_steps), args.repeats)}
            if not args.no_ppo:
                row["ppo"] = compare(partial(ppo_rate, num_envs=num_envs, workers=workers,
                                             updates=args.ppo_updates,
                                             num_steps=args.ppo_steps), args.repeats)
            rows.append(row)
            print(json.dumps(row), flush=True)
    finally:
        ray.shutdown()
    result = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
                   f"Python {platform.python_version()}, ray {ray.__version__}",
        "load_1min_start": round(load_start, 2),
        "load_1min_end": round(load(), 2),
        "ray_init_s": ray_start_s,
        "envs_per_worker": args.envs_per_worker,
        "env_steps": args.env_steps,
        "ppo_updates": args.ppo_updates,
        "ppo_steps": args.ppo_steps,
        "wall_s": round(time.perf_counter() - began, 1),
        "rows": rows,
    }
    name = "ray" + (f"-{args.tag}" if args.tag else "")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    write_markdown(result, RESULTS / f"{name}.md")
    print((RESULTS / f"{name}.md").read_text())


def write_markdown(result: dict, path: Path) -> None:
    lines = [
        "# Ray env workers vs AsyncVectorEnv",
        "",
        f"Machine: {result['machine']}; 1-min load average {result['load_1min_start']} at "
        f"start, {result['load_1min_end']} at the end (other jobs included); the benchmark "
        f"took {result.get('wall_s', '?')} s. Ray start-up "
        f"(`ray.init`, not in the rates): {result['ray_init_s']} s. "
        f"Env steps/s on the same cores: AsyncVectorEnv with one env per process, one "
        f"process per worker, versus Ray with {result['envs_per_worker']} envs per worker. "
        "PPO steps/s (end to end, start-up excluded) with the same envs: one process per env "
        "versus the Ray workers. "
        "Medians of the repeats (each repeat: baseline, then Ray).",
        "",
        "| workers (cores) | Ray envs | env steps/s: Async | Ray | Ray/Async "
        "| PPO steps/s: Async | Ray | Ray/Async |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in result["rows"]:
        env, ppo = row["env"], row.get("ppo")
        ppo_cells = (f"{ppo['async_median']} | {ppo['ray_median']} | x{ppo['ray_vs_async']}"
                     if ppo else "- | - | -")
        lines.append(f"| {row['workers']} | {row['num_envs']} | {env['async_median']} | "
                     f"{env['ray_median']} | x{env['ray_vs_async']} | {ppo_cells} |")
    path.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
