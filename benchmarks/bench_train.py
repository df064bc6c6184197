"""Training benchmarks: end-to-end PPO throughput, the bundled policy's training run and its
evaluation. Writes benchmarks/results/train.json and train.md.

    python benchmarks/bench_train.py --train-run runs/forward --command "jetbot-train ..." \
        --command-wall-s 398                                            # all three
    python benchmarks/bench_train.py --throughput-steps 2048 --episodes 0   # throughput only

Timings depend on what else the machine runs; the recorded ones say what the CPU was shared with.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def measure_throughput(steps: int, num_envs: int) -> dict:
    from jetbot_rt.train.ppo import PPOArgs, train

    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        summary = train(PPOArgs(total_timesteps=steps, num_envs=num_envs, out=out,
                                progress=False))
        total = time.perf_counter() - start
    return {
        "timesteps": summary["global_step"],
        "num_envs": num_envs,
        "env_steps_per_s_training_loop": summary["steps_per_s"],
        "env_steps_per_s_with_startup_and_export": round(summary["global_step"] / total, 1),
    }


def read_training_run(run: Path) -> dict:
    with (run / "metrics.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    last = rows[-1]
    return {
        "run_dir": str(run),
        "timesteps": int(last["global_step"]),
        "updates": int(last["update"]),
        "training_wall_s": float(last["wall_s"]),
        "env_steps_per_s": round(int(last["global_step"]) / float(last["wall_s"]), 1),
        "last_train_success_rate": float(last["success_rate"] or 0),
        "last_train_mean_final_distance": float(last["mean_final_distance"] or "nan"),
    }


def write_markdown(result: dict, path: Path) -> None:
    lines = ["# Training benchmark", "", f"Machine: {result['machine']}", ""]
    if result.get("note"):
        lines += [f"Note: {result['note']}", ""]
    if "throughput" in result:
        t = result["throughput"]
        lines += [
            "## PPO throughput (end to end: render, policy, update)", "",
            f"- {t['timesteps']} steps, {t['num_envs']} env processes: "
            f"**{t['env_steps_per_s_training_loop']} env steps/s** in the training loop, "
            f"{t['env_steps_per_s_with_startup_and_export']} steps/s including worker start "
            "and ONNX export", "",
        ]
    if "bundled_training" in result:
        b = result["bundled_training"]
        lines += [
            "## The bundled policy's training run", "",
            f"- command: `{result.get('bundled_command', '')}`",
            f"- {b['timesteps']} env steps in **{b['training_wall_s']:.0f} s** "
            f"({b['training_wall_s'] / 60:.1f} min) of training wall-clock, "
            f"{b['env_steps_per_s']} env steps/s"
            + (f"; the whole command (worker start, training, ONNX export, curve) "
               f"{b['command_wall_s']:.0f} s" if b.get("command_wall_s") else ""),
            f"- training episodes at the end (last 20, stochastic actions): success "
            f"{b['last_train_success_rate']:.0%}, mean final distance "
            f"{b['last_train_mean_final_distance']:.3f} m", "",
        ]
    if "eval" in result:
        e = result["eval"]
        lines += [
            "## Evaluation of jetbot_rt/policies/forward.onnx", "",
            f"- `jetbot-train eval --episodes {e['episodes']} --json`: "
            f"**success {e['success_rate']:.0%}** over {e['episodes']} episodes "
            f"(final distance < {e['success_distance']} m), mean final distance "
            f"{e['mean_final_distance']:.3f} m (max {e['max_final_distance']:.3f} m), "
            f"mean return {e['mean_return']:.4g}", "",
        ]
    path.write_text("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--throughput-steps", type=int, default=2048)
    parser.add_argument("--num-envs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--train-run", type=Path, help="output dir of the bundled policy's run")
    parser.add_argument("--command", default="", help="the command that made --train-run")
    parser.add_argument("--command-wall-s", type=float,
                        help="wall-clock of that whole command, timed outside it")
    parser.add_argument("--episodes", type=int, default=100, help="0: skip the evaluation")
    parser.add_argument("--note", default="", help="e.g. what else shared the CPU")
    args = parser.parse_args()

    result: dict = {
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, {platform.platform()}",
        "note": args.note,
    }
    previous = RESULTS / "train.json"
    if previous.exists():
        result = {**json.loads(previous.read_text()), **result}
    if args.throughput_steps > 0:
        result["throughput"] = measure_throughput(args.throughput_steps, args.num_envs)
    if args.train_run is not None:
        result["bundled_training"] = read_training_run(args.train_run)
        if args.command_wall_s is not None:
            result["bundled_training"]["command_wall_s"] = args.command_wall_s
        result["bundled_command"] = args.command or result.get("bundled_command", "")
    if args.episodes > 0:
        from jetbot_rt.train.evaluate import evaluate

        result["eval"] = evaluate(None, episodes=args.episodes, num_workers=args.num_envs)
        result["eval"]["policy"] = "jetbot_rt/policies/forward.onnx"
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "train.json").write_text(json.dumps(result, indent=2) + "\n")
    write_markdown(result, RESULTS / "train.md")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
