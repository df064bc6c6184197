"""Training benchmarks: end-to-end PPO throughput, the bundled policy's training run and its
evaluation. Writes benchmarks/results/train[-TAG].json and .md.

    python benchmarks/bench_train.py                          # throughput, 1 and 2 processes
    python benchmarks/bench_train.py --processes 2            # the issue's figure only (~3 min)
    python benchmarks/bench_train.py --episodes 100           # and evaluate the bundled policy
    python benchmarks/bench_train.py --processes 1 2 4 8 16 --tag h100   # a big host
    python benchmarks/bench_train.py --throughput-steps 0 --train-run runs/forward \
        --command "jetbot-train ..." --command-wall-s 398     # record a training run

Throughput is PPO end to end, in the same run, with three settings per number of env worker
processes: the 224x224 path (the first bundled network, pool 4, physics at 240 Hz, the old
update recipe), the training size with the first network and that old recipe (8 epochs x 4
minibatches, the action distribution checking its arguments, the learner computing every
step's actions), and the training size with today's defaults for forward (``ppo_args``: the
6x6 stride-4 first layer, 4 epochs x 2 minibatches, the policy run in the env workers).

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

from versions import stamp

RESULTS = Path(__file__).resolve().parent / "results"


SETTINGS = ("224", "56-old", "train")
"""The throughput runs of each process count, baselines first."""
OLD_RECIPE = {"update_epochs": 8, "num_minibatches": 4}
"""PPOArgs before the update was made cheaper (issue 10); the old settings also have the
first network (5x5 stride-2 first layer) and the learner computing every step's actions."""


def measure_throughput(steps: int, num_envs: int, setting: str) -> dict:
    from jetbot_rt.config.sections import Config
    from jetbot_rt.train.hyperparams import LEGACY_IMAGE_SIZE, LEGACY_POOL, ModelConfig, ppo_args
    from jetbot_rt.train.model import ActorCritic
    from jetbot_rt.train.ppo import train

    config, model, recipe = Config(), ModelConfig(), {}
    if setting == "224":
        config.sim.physics_hz = 240.0
        model = ModelConfig(image_size=LEGACY_IMAGE_SIZE, pool=LEGACY_POOL)
    if setting in ("224", "56-old"):
        recipe = OLD_RECIPE
    ActorCritic.validate_args = setting != "train"
    try:
        with tempfile.TemporaryDirectory() as out:
            args = ppo_args("forward", {"total_timesteps": steps, "num_envs": num_envs,
                                        "out": out, "progress": False, **recipe})
            args.config = config
            if setting != "train":  # the first network, per step through the learner
                args.model, args.sample_in_workers = model, False
            start = time.perf_counter()
            summary = train(args)
            total = time.perf_counter() - start
    finally:
        ActorCritic.validate_args = False
    return {
        "path": setting,
        "image_size": args.model.image_size,
        "first_layer": f"{args.model.first_kernel}x{args.model.first_kernel} stride "
                       f"{args.model.first_stride}",
        "sample_in_workers": args.sample_in_workers,
        "physics_hz": config.sim.physics_hz,
        "update_epochs": args.update_epochs,
        "num_minibatches": args.num_minibatches,
        "update_threads": args.update_threads,
        "validate_args": setting != "train",
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
        rows = result["throughput"]
        new = next(r for r in rows if r["path"] == "train")
        lines += [
            "## PPO throughput (end to end: render, policy, update)", "",
            f"{rows[0]['timesteps']} env steps per run, one env per worker process; env "
            "steps/s in the training loop, the best of the rounds (each round runs every "
            "setting once, in this order) and all of them in brackets. 1-min load "
            f"average {result.get('loadavg_1min_at_start')} at start, "
            f"{result.get('loadavg_1min_at_end')} at the end.", "",
            "| worker processes | 224x224 path (pool 4, 240 Hz, old recipe) | "
            f"{new['image_size']}x{new['image_size']}, old recipe (8 epochs x 4 minibatches, "
            "first network, actions from the learner each step) "
            f"| {new['image_size']}x{new['image_size']}, {new['physics_hz']:g} Hz, now "
            f"({new['update_epochs']} epochs x {new['num_minibatches']} minibatches, first "
            f"layer {new.get('first_layer', '5x5 stride 2')}, "
            f"{'policy in the workers' if new.get('sample_in_workers') else 'learner'}) "
            "| now / 224 | now / old recipe |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for n in sorted({r["num_envs"] for r in rows}):
            runs = [[r["env_steps_per_s_training_loop"] for r in rows
                     if r["num_envs"] == n and r["path"] == setting] for setting in SETTINGS]
            shown = [f"{max(v)}" + (f" (of {', '.join(map(str, v))})" if len(v) > 1 else "")
                     if v else "-" for v in runs]
            now = max(runs[2]) if runs[2] else None
            ratios = [f"x{now / max(v):.2f}" if now and v else "-" for v in runs[:2]]
            lines.append(f"| {n} | {shown[0]} | {shown[1]} | **{shown[2]}** | "
                         f"{ratios[0]} | {ratios[1]} |")
        lines.append("")
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
    parser.add_argument("--throughput-steps", type=int, default=4096,
                        help="env steps per throughput run (0: skip the throughput)")
    parser.add_argument("--num-envs", type=int, default=os.cpu_count() or 1,
                        help="eval worker processes")
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 2],
                        help="env worker processes of each throughput run")
    parser.add_argument("--tag", default="", help="write train-TAG.json / train-TAG.md")
    parser.add_argument("--train-run", type=Path, help="output dir of the bundled policy's run")
    parser.add_argument("--command", default="", help="the command that made --train-run")
    parser.add_argument("--command-wall-s", type=float,
                        help="wall-clock of that whole command, timed outside it")
    parser.add_argument("--episodes", type=int, default=0,
                        help="evaluate the bundled policy over this many episodes (0: skip)")
    parser.add_argument("--rounds", type=int, default=1,
                        help="run every setting this many times, interleaved (a shared machine)")
    parser.add_argument("--settings", nargs="+", choices=SETTINGS, default=list(SETTINGS),
                        help="throughput settings to run (default: all three)")
    parser.add_argument("--note", default="", help="e.g. what else shared the CPU")
    args = parser.parse_args()

    result: dict = {
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, {platform.platform()}",
        "note": args.note,
    }
    name = f"train-{args.tag}" if args.tag else "train"
    previous = RESULTS / f"{name}.json"
    if previous.exists():
        before = json.loads(previous.read_text())
        for key in ("bundled_training", "eval"):  # kept from an earlier run unless re-measured:
            if isinstance(before.get(key), dict):  # they keep that run's versions (None: unknown)
                before[key].setdefault("versions", before.get("versions"))
        result = {**before, **result}
        if isinstance(result.get("throughput"), dict):  # one run of the format before issue 10
            del result["throughput"]
    if args.throughput_steps > 0:
        result["loadavg_1min_at_start"] = round(os.getloadavg()[0], 2)
        result["throughput"] = [
            {**measure_throughput(args.throughput_steps, n, setting), "round": k}
            for n in args.processes for k in range(args.rounds) for setting in args.settings
        ]
        result["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    if args.train_run is not None:
        result["bundled_training"] = stamp(read_training_run(args.train_run))
        if args.command_wall_s is not None:
            result["bundled_training"]["command_wall_s"] = args.command_wall_s
        result["bundled_command"] = args.command or result.get("bundled_command", "")
    if args.episodes > 0:
        from jetbot_rt.train.evaluate import evaluate

        result["eval"] = evaluate(None, episodes=args.episodes, num_workers=args.num_envs)
        result["eval"]["policy"] = "jetbot_rt/policies/forward.onnx"
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    write_markdown(result, RESULTS / f"{name}.md")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
