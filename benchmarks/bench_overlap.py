"""PPO end to end against the simulator alone, in the same run (issue 21, target 1): for each
task, the env steps/s of N processes stepping the task's env with random commands
(``bench_sim.bench_env``), then ``jetbot-train``'s PPO with N envs in the arms ``--arms``
names (default all): synchronous, ``--overlap`` with one barrier a rollout (every worker given
its next rollout when the last one has answered: the code of 38dce43..054ebc4,
``WorkerRollouts.pipelined`` off), ``--overlap`` as it is (each worker given its next rollout
the moment it answers) and ``--overlap --balance`` (a rollout's steps shared among the workers
as they come), rounds interleaved so that a drift of the machine touches every arm alike.

    python benchmarks/bench_overlap.py --num-envs 16 --device cuda --tag h200-16

Writes overlap[-TAG].json and .md to --out. Each PPO run is the task's default recipe
(``ppo_args``) for ``--steps`` env steps; its figure is the training loop's env steps/s
(``steps_per_s`` of the last metrics row: from the first rollout's start, worker start-up and
export left out, as the simulator's figure leaves out its start-up). Each overlapped run
also gives the median time from the first worker's answer read to the last's, per rollout
(``spread_ms``: what the barrier keeps the first workers waiting), and every run where the
learner's time goes: the period between updates, its wait for the workers' answers and the
update (``period_ms``, ``gather_ms``, ``update_ms``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch  # noqa: F401 - before pybullet (bench_sim): the other order segfaults on some builds
from bench_sim import PATHS, bench_env, machine
from versions import write_results

ARMS = {"sync": (False, False, False), "barrier": (True, False, False),
        "overlap": (True, True, False), "balanced": (True, True, True)}
"""Each arm's (``--overlap``, ``WorkerRollouts.pipelined``, ``--balance``)."""
ARM_TITLES = {"sync": "PPO sync", "barrier": "--overlap, one barrier", "overlap": "--overlap now",
              "balanced": "--overlap --balance"}


def ppo_steps_per_s(task: str, num_envs: int, steps: int, arm: str, device: str) -> dict:
    from jetbot_rt.train import ppo, rollout
    from jetbot_rt.train.hyperparams import ppo_args
    from jetbot_rt.train.ppo import train

    overlap, pipelined, balance = ARMS[arm]
    spreads: list[float] = []
    waits: list[float] = []
    updates: list[float] = []
    gather, update = rollout.WorkerCalls.gather, ppo.ppo_update

    def timed(calls, *a, **k):
        began = time.perf_counter()
        answers = gather(calls, *a, **k)
        waits.append(time.perf_counter() - began)
        spreads.append(calls.last_spread)
        return answers

    def timed_update(*a, **k):
        began = time.perf_counter()
        stats = update(*a, **k)  # its losses' .item() wait for the GPU
        updates.append(time.perf_counter() - began)
        return stats

    with tempfile.TemporaryDirectory() as out:
        args = ppo_args(task, {"total_timesteps": steps, "num_envs": num_envs, "out": out,
                               "progress": False, "overlap": overlap, "device": device,
                               "balance": balance})
        rollout.WorkerRollouts.pipelined = pipelined
        rollout.WorkerCalls.gather = timed
        ppo.ppo_update = timed_update
        start = time.perf_counter()
        try:
            summary = train(args)
        finally:
            rollout.WorkerRollouts.pipelined = True
            rollout.WorkerCalls.gather = gather
            ppo.ppo_update = update
        wall = time.perf_counter() - start

    def median_ms(seconds: list[float]) -> float | None:
        return round(1000 * statistics.median(seconds), 1) if seconds else None

    # a rollout's period against what the learner spends waiting for the workers' answers
    # and updating: a wait near 0 with an update near the period means the learner paces
    # the run, not the workers
    return {"arm": arm, "timesteps": summary["global_step"], "spread_ms": median_ms(spreads),
            "gather_ms": median_ms(waits), "update_ms": median_ms(updates),
            "period_ms": round(1000 * summary["wall_s"] / max(summary["updates"], 1), 1),
            "steps_per_s": summary["steps_per_s"], "wall_s_with_startup": round(wall, 1),
            "update_epochs": args.update_epochs, "num_minibatches": args.num_minibatches,
            "num_steps": args.num_steps}


def markdown(result: dict) -> str:
    m = result["machine"]
    arms = result["arms"]
    lines = [
        "# PPO end to end against the simulator alone", "",
        f"Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}, learner on "
        f"{result['device']}; 1-min load average {m['loadavg_1min_at_start']} at start, "
        f"{m['loadavg_1min_at_end']} at the end. Command: `{result['command']}`.", "",
        f"{result['num_envs']} env processes. Simulator alone: `JetbotEnv.step` with random "
        f"commands, {result['env_steps']} steps a process. PPO: the task's default recipe, "
        f"{result['steps']} env steps a run, {result['rounds']} rounds (the arms "
        f"interleaved: {', '.join(ARM_TITLES[a] for a in arms)}); env steps/s, the median "
        "and every run in brackets, then the share of the simulator alone; the spread is "
        "the median time from a rollout's first worker answer read to its last (ms).", "",
        "| task | simulator alone | " + " | ".join(ARM_TITLES[a] for a in arms)
        + " | spread (ms) |",
        "| --- | --- | " + " | ".join("---" for _ in arms) + " | --- |",
    ]

    def cell(arm: dict, total: float) -> str:
        runs = ", ".join(map(str, arm["runs"]))
        return f"{arm['median']} ({runs}), {arm['median'] / total:.1%}"

    for row in result["tasks"]:
        total = row["sim"]["steps_per_s_total"]
        spreads = " / ".join(f"{a} {row[a]['spread_ms']}" for a in arms
                             if row[a]["spread_ms"] is not None)
        lines.append(f"| {row['task']} | {total} | "
                     + " | ".join(cell(row[a], total) for a in arms) + f" | {spreads} |")
    lines += ["", "Where a rollout's time goes in the learner, medians over a run's rollouts "
              "(ms; the median run of each arm): the period between updates, the wait for "
              "the workers' answers (the overlapped arms) and the update.", "",
              "| task | arm | period | wait for answers | update |",
              "| --- | --- | --- | --- | --- |"]
    for row in result["tasks"]:
        for a in arms:
            runs = sorted(row[a]["detail"], key=lambda r: r["steps_per_s"])
            run = runs[len(runs) // 2]
            lines.append(f"| {row['task']} | {ARM_TITLES[a]} | {run.get('period_ms')} | "
                         f"{run.get('gather_ms')} | {run.get('update_ms')} |")
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
    parser.add_argument("--arms", nargs="+", choices=list(ARMS), default=list(ARMS))
    args = parser.parse_args()

    result: dict = {"machine": machine(), "num_envs": args.num_envs, "steps": args.steps,
                    "env_steps": args.env_steps, "rounds": args.rounds, "device": args.device,
                    "command": "python benchmarks/bench_overlap.py " + " ".join(sys.argv[1:]),
                    "arms": args.arms, "tasks": []}
    for task in args.tasks:
        sim = bench_env({**PATHS["train"], "task": task}, args.num_envs, args.env_steps)
        runs: dict[str, list[dict]] = {arm: [] for arm in args.arms}
        for _ in range(args.rounds):
            for arm in args.arms:
                run = ppo_steps_per_s(task, args.num_envs, args.steps, arm, args.device)
                runs[arm].append(run)
                print(task, run, flush=True)
        row = {"task": task, "sim": sim}
        for arm in args.arms:
            rates = [r["steps_per_s"] for r in runs[arm]]
            spreads = [r["spread_ms"] for r in runs[arm] if r["spread_ms"] is not None]
            row[arm] = {"median": statistics.median(rates), "runs": rates,
                        "spread_ms": statistics.median(spreads) if spreads else None,
                        "detail": runs[arm]}
        total = sim["steps_per_s_total"]
        for arm in args.arms:
            row[f"{arm}_over_sim"] = round(row[arm]["median"] / total, 3)
        result["tasks"].append(row)
        print(task, "sim", sim["steps_per_s_total"], flush=True)
    result["machine"]["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    name = f"overlap-{args.tag}" if args.tag else "overlap"
    write_results(args.out, name, result, markdown(result))


if __name__ == "__main__":
    main()
