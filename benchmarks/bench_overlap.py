"""PPO end to end against the simulator alone, in the same run (issue 21, target 1): for each
task, the env steps/s of N processes stepping the task's env with random commands
(``bench_sim.bench_env``), then ``jetbot-train``'s PPO with N envs, synchronous and with
``--overlap`` (the workers collect the next rollout while the learner updates), rounds
interleaved so that a drift of the machine touches both alike.

    python benchmarks/bench_overlap.py --num-envs 16 --device cuda --tag h200-16

Writes overlap[-TAG].json and .md to --out. Each PPO run is the task's default recipe
(``ppo_args``) for ``--steps`` env steps; its figure is the training loop's env steps/s
(``steps_per_s`` of the last metrics row: from the first rollout's start, worker start-up and
export left out, as the simulator's figure leaves out its start-up).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch  # noqa: F401 - before pybullet (bench_sim): the other order segfaults on some builds
from bench_sim import PATHS, bench_env, machine
from versions import stamp


def ppo_steps_per_s(task: str, num_envs: int, steps: int, overlap: bool, device: str) -> dict:
    from jetbot_rt.train.hyperparams import ppo_args
    from jetbot_rt.train.ppo import train

    with tempfile.TemporaryDirectory() as out:
        args = ppo_args(task, {"total_timesteps": steps, "num_envs": num_envs, "out": out,
                               "progress": False, "overlap": overlap, "device": device})
        start = time.perf_counter()
        summary = train(args)
        wall = time.perf_counter() - start
    return {"overlap": overlap, "timesteps": summary["global_step"],
            "steps_per_s": summary["steps_per_s"], "wall_s_with_startup": round(wall, 1),
            "update_epochs": args.update_epochs, "num_minibatches": args.num_minibatches,
            "num_steps": args.num_steps}


def markdown(result: dict) -> str:
    m = result["machine"]
    lines = [
        "# PPO end to end against the simulator alone", "",
        f"Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}, learner on "
        f"{result['device']}; 1-min load average {m['loadavg_1min_at_start']} at start, "
        f"{m['loadavg_1min_at_end']} at the end. Command: `{result['command']}`.", "",
        f"{result['num_envs']} env processes. Simulator alone: `JetbotEnv.step` with random "
        f"commands, {result['env_steps']} steps a process. PPO: the task's default recipe, "
        f"{result['steps']} env steps a run, {result['rounds']} rounds (sync, overlap "
        "interleaved); the median and every run in brackets.", "",
        "| task | simulator alone | PPO sync | PPO --overlap | sync / sim | overlap / sim "
        "| overlap / sync |", "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in result["tasks"]:
        sync, over = row["sync"], row["overlap"]
        lines.append(
            f"| {row['task']} | {row['sim']['steps_per_s_total']} | {sync['median']} "
            f"({', '.join(map(str, sync['runs']))}) | {over['median']} "
            f"({', '.join(map(str, over['runs']))}) | {row['sync_over_sim']:.0%} | "
            f"{row['overlap_over_sim']:.0%} | x{row['overlap_over_sync']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=["forward", "seek"])
    parser.add_argument("--num-envs", type=int, default=os.cpu_count())
    parser.add_argument("--steps", type=int, default=32768)
    parser.add_argument("--env-steps", type=int, default=900)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    parser.add_argument("--tag", default="")
    args = parser.parse_args()

    result: dict = {"machine": machine(), "num_envs": args.num_envs, "steps": args.steps,
                    "env_steps": args.env_steps, "rounds": args.rounds, "device": args.device,
                    "command": "python benchmarks/bench_overlap.py " + " ".join(sys.argv[1:]),
                    "tasks": []}
    for task in args.tasks:
        sim = bench_env({**PATHS["train"], "task": task}, args.num_envs, args.env_steps)
        runs: dict[bool, list[dict]] = {False: [], True: []}
        for _ in range(args.rounds):
            for overlap in (False, True):
                run = ppo_steps_per_s(task, args.num_envs, args.steps, overlap, args.device)
                runs[overlap].append(run)
                print(task, run, flush=True)
        row = {"task": task, "sim": sim}
        for overlap, key in ((False, "sync"), (True, "overlap")):
            rates = [r["steps_per_s"] for r in runs[overlap]]
            row[key] = {"median": statistics.median(rates), "runs": rates,
                        "detail": runs[overlap]}
        total = sim["steps_per_s_total"]
        row["sync_over_sim"] = round(row["sync"]["median"] / total, 3)
        row["overlap_over_sim"] = round(row["overlap"]["median"] / total, 3)
        row["overlap_over_sync"] = round(row["overlap"]["median"] / row["sync"]["median"], 2)
        result["tasks"].append(row)
        print(task, "sim", sim["steps_per_s_total"], flush=True)
    result["machine"]["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    name = f"overlap-{args.tag}" if args.tag else "overlap"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{name}.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    (args.out / f"{name}.md").write_text(markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
