"""Does PPO learn as well with ``--overlap`` and ``--overlap --balance`` as synchronous? (issue
21, target 1: "keep PPO's semantics or say exactly what changes and show it learns as well").
Trains the task's default recipe once per arm and seed, the arms interleaved within each seed
so that a drift of the machine touches every arm alike, then evaluates each policy on the same
held-out episodes:

    python benchmarks/bench_learn_alike.py --task forward --seeds 1 2 3 --num-envs 16 \\
        --device cuda --tag h200-16

Writes learn_alike[-TAG].json and .md to --out: per run the env steps, the wall time, the
training curve's last rows (mean return, success) and the first env step where the training
success reached ``--reach``, and the evaluation's success over ``--episodes`` episodes
(seeds from ``--eval-seed``)."""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from versions import cpu_model, write_results

ARMS = {"sync": [], "overlap": ["--overlap"], "balanced": ["--overlap", "--balance"]}
TITLES = {"sync": "synchronous", "overlap": "`--overlap`", "balanced": "`--overlap --balance`"}


def jetbot_train() -> list[str]:
    found = shutil.which("jetbot-train")
    if found is None:
        sys.exit("bench_learn_alike: jetbot-train is not on PATH "
                 "(install the project: pip install -e .)")
    return [found]


def curve(metrics: Path, reach: float) -> dict:
    with metrics.open() as f:
        rows = list(csv.DictReader(f))
    scored = [r for r in rows if r["success_rate"] != ""]
    last = scored[-5:]
    reached = next((int(r["global_step"]) for r in scored if float(r["success_rate"]) >= reach),
                   None)
    return {"updates": len(rows), "env_steps": int(rows[-1]["global_step"]),
            "wall_s": float(rows[-1]["wall_s"]),
            "last5_mean_return": round(statistics.mean(float(r["mean_return"]) for r in last), 2),
            "last5_success": round(statistics.mean(float(r["success_rate"]) for r in last), 3),
            "first_step_at_reach": reached}


def run(task: str, arm: str, seed: int, args: argparse.Namespace, work: Path) -> dict:
    out = work / f"{arm}-{seed}"
    train = [*jetbot_train(), "train", "--task", task, "--algo", "ppo", "--device", args.device,
             "--num-envs", str(args.num_envs), "--seed", str(seed), "--out", str(out),
             "--no-progress", *ARMS[arm], *args.train_args]
    if args.timesteps:
        train += ["--total-timesteps", str(args.timesteps)]
    subprocess.run(train, check=True, stdout=subprocess.DEVNULL)
    evaluation = subprocess.run(
        [*jetbot_train(), "eval", "--task", task, "--policy", str(out / "policy.onnx"),
         "--episodes", str(args.episodes), "--seed", str(args.eval_seed), "--num-envs",
         str(args.num_envs), "--json", "--no-progress"],
        check=True, capture_output=True, text=True)
    result = json.loads(evaluation.stdout)
    row = {"arm": arm, "seed": seed, **curve(out / "metrics.csv", args.reach),
           "eval_success": result["success_rate"], "eval_mean_return": result["mean_return"]}
    print(json.dumps(row), flush=True)
    return row


def markdown(result: dict) -> str:
    lines = [f"# Does PPO learn {result['task']} as well overlapped and balanced?", "",
             f"Machine: {result['cpu']}, {result['cores']} cores; learner on {result['device']}. "
             f"Command: `{result['command']}`.", "",
             f"Each run: the task's default recipe ({result['train_args'] or 'no overrides'}), "
             f"{result['num_envs']} envs; evaluation {result['episodes']} episodes from seed "
             f"{result['eval_seed']}. Training success: the last 5 updates' (each the last 20 "
             f"episodes'); reached: the first env step where it was >= {result['reach']:.0%}.",
             "", "| arm | seed | env steps | wall s | last-5 return | last-5 success | "
             "reached at | eval success |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in result["runs"]:
        lines.append(f"| {TITLES[r['arm']]} | {r['seed']} | {r['env_steps']} | {r['wall_s']} | "
                     f"{r['last5_mean_return']} | {r['last5_success']:.0%} | "
                     f"{r['first_step_at_reach'] or 'never'} | {r['eval_success']:.0%} |")
    lines += ["", "| arm | eval success, mean (runs) | last-5 return, mean |",
              "| --- | --- | --- |"]
    for arm in result["arms"]:
        runs = [r for r in result["runs"] if r["arm"] == arm]
        evals = [r["eval_success"] for r in runs]
        lines.append(f"| {TITLES[arm]} | {statistics.mean(evals):.1%} "
                     f"({', '.join(f'{e:.0%}' for e in evals)}) | "
                     f"{statistics.mean(r['last5_mean_return'] for r in runs):.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="forward")
    parser.add_argument("--arms", nargs="+", choices=list(ARMS), default=list(ARMS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    parser.add_argument("--num-envs", type=int, default=os.cpu_count())
    parser.add_argument("--device", default="auto")
    parser.add_argument("--timesteps", type=int, default=0, help="0: the recipe's")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--eval-seed", type=int, default=20000)
    parser.add_argument("--reach", type=float, default=0.9)
    parser.add_argument("--train-args", nargs=argparse.REMAINDER, default=[],
                        help="the rest goes to jetbot-train train as is")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    parser.add_argument("--tag", default="")
    args = parser.parse_args()

    runs = []
    with tempfile.TemporaryDirectory() as work:
        for seed in args.seeds:
            for arm in args.arms:
                runs.append(run(args.task, arm, seed, args, Path(work)))
    result = {"task": args.task, "cpu": cpu_model(), "cores": os.cpu_count(),
              "device": args.device, "num_envs": args.num_envs, "episodes": args.episodes,
              "eval_seed": args.eval_seed, "reach": args.reach, "arms": args.arms,
              "train_args": " ".join(args.train_args + (
                  [f"--total-timesteps {args.timesteps}"] if args.timesteps else [])),
              "command": "python benchmarks/bench_learn_alike.py " + " ".join(sys.argv[1:]),
              "runs": runs}
    name = f"learn_alike-{args.tag}" if args.tag else "learn_alike"
    write_results(args.out, name, result, markdown(result))


if __name__ == "__main__":
    main()
