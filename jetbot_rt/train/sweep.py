"""``jetbot-train sweep``: several seeds (and configs, e.g. randomization ranges) trained at once
across a Ray cluster, one table of results at the end.

A trial is one ordinary ``train`` run (its envs in ``num_envs`` processes on the node it
lands on, so it asks Ray for that many CPUs; one env runs in the trial's own process),
then ``evaluate`` of its policy on the task's evaluation episodes under the trial's config.
The trial's files (checkpoint, ONNX, metrics, curve) come back to the driver through Ray, so
the nodes need no shared disk: ``OUT/<trial>/``. ``OUT/sweep.csv`` and ``OUT/sweep.md`` hold
the table, which is also printed. A trial whose node dies is run again from the start
elsewhere (Ray's task retries).
"""

from __future__ import annotations

import argparse
import csv
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

from jetbot_rt.errors import UsageError

TRIAL_FILES = ("checkpoint.pt", "policy.onnx", "metrics.csv", "learning_curve.png")
COLUMNS = ("trial", "config", "seed", "eval_success_rate", "eval_mean_return",
           "train_success_rate", "global_step", "steps_per_s", "wall_s", "node")


def add_parser(sub: Any, tasks: list[str]) -> argparse.ArgumentParser:
    sweep = sub.add_parser(
        "sweep", help="train several seeds / configs across a Ray cluster, one results table",
        description="Train several seeds (and configs, e.g. randomization ranges) at once "
        "across a Ray cluster, evaluate each policy, print one table of results. Each trial "
        "is a train run with the task's PPO defaults and its config's [train] table.")
    sweep.add_argument("--task", default="forward", choices=tasks, help="the task to learn")
    sweep.add_argument("--timesteps", type=int, help="env steps per trial (default: the "
                       "task's, or the config's [train] total_timesteps)")
    sweep.add_argument("--num-envs", type=int, default=2,
                       help="env processes per trial (and the CPUs it asks Ray for)")
    sweep.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3],
                       help="one trial per seed and config")
    sweep.add_argument("--config", nargs="+", metavar="TOML",
                       help="one or more TOML configs (e.g. [randomize] ranges, a [train] "
                            "table); each is trained with every seed and evaluated under "
                            "itself (default: the built-in config)")
    sweep.add_argument("--eval-episodes", type=int, default=20,
                       help="evaluation episodes per trial")
    sweep.add_argument("--ray", nargs="?", const="local", default="local", metavar="ADDRESS",
                       help="Ray cluster: 'local' (Ray on this machine), 'auto' or HOST:PORT")
    sweep.add_argument("--out", required=True, help="output directory")
    return sweep


def run_trial(name: str, args: Any, config_name: str, eval_episodes: int) -> dict[str, Any]:
    """One trial on whichever node Ray chose: train, evaluate, hand the files back."""
    import ray

    from jetbot_rt.train.evaluate import evaluate
    from jetbot_rt.train.ppo import train

    with tempfile.TemporaryDirectory(prefix=f"jetbot-sweep-{name}-") as out:
        summary = train(replace(args, out=out))
        result = evaluate(summary["policy"], task=args.task, episodes=eval_episodes,
                          num_workers=args.num_envs, config=args.config)
        with (Path(out) / "metrics.csv").open() as handle:
            last = list(csv.DictReader(handle))[-1]
        files = {f: (Path(out) / f).read_bytes() for f in TRIAL_FILES if (Path(out) / f).exists()}
    row = {
        "trial": name, "config": config_name, "seed": args.seed,
        "eval_success_rate": result["success_rate"],
        "eval_mean_return": round(float(result["mean_return"]), 1),
        "train_success_rate": last.get("success_rate", ""),
        "global_step": summary["global_step"], "steps_per_s": summary["steps_per_s"],
        "wall_s": round(summary["wall_s"], 1),
        "node": ray.get_runtime_context().get_node_id()[:8],
    }
    return {"row": row, "files": files}


def sweep(namespace: argparse.Namespace) -> list[dict[str, Any]]:
    from jetbot_rt.train.cli import _load_train_config
    from jetbot_rt.train.ppo import _prepare_out, ppo_args
    from jetbot_rt.train.ray_workers import connect

    for name, value in (("--timesteps", namespace.timesteps), ("--num-envs", namespace.num_envs),
                        ("--eval-episodes", namespace.eval_episodes)):
        if value is not None and value <= 0:
            raise UsageError(f"{name} must be > 0, got {value}")
    out = Path(namespace.out)
    _prepare_out(out)
    paths = namespace.config or [None]
    configs = [(Path(p).stem if p else "default", *_load_train_config(p)) for p in paths]
    if len({name for name, _, _ in configs}) != len(configs):
        raise UsageError("--config files must have different names (they name the trials)")
    owns = connect(namespace.ray)
    import ray

    try:
        remote = ray.remote(num_cpus=namespace.num_envs, max_retries=2)(run_trial)
        refs = []
        for config_name, config, table in configs:
            for seed in namespace.seeds:
                name = f"{config_name}-seed{seed}"
                options = {**table, "num_envs": namespace.num_envs, "seed": seed,
                           "workers": 0 if namespace.num_envs == 1 else None, "ray": None,
                           "progress": False, "update_threads": namespace.num_envs,
                           "device": "cpu"}  # Ray gives a trial CPUs, not a GPU
                if namespace.timesteps is not None:
                    options["total_timesteps"] = namespace.timesteps
                args = ppo_args(namespace.task, options)
                args.config = config
                refs.append(remote.remote(name, args, config_name, namespace.eval_episodes))
        results = ray.get(refs)
    except KeyboardInterrupt:
        for ref in refs:
            ray.cancel(ref, force=True)
        raise
    finally:
        if owns:
            ray.shutdown()
    rows = []
    for result in results:
        row = result["row"]
        trial_dir = out / row["trial"]
        trial_dir.mkdir(exist_ok=True)
        for file_name, data in result["files"].items():
            (trial_dir / file_name).write_bytes(data)
        rows.append(row)
    write_table(rows, out)
    return rows


def write_table(rows: list[dict[str, Any]], out: Path) -> None:
    with (out / "sweep.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + " --- |" * len(COLUMNS)]
    lines += ["| " + " | ".join(str(row[c]) for c in COLUMNS) + " |" for row in rows]
    (out / "sweep.md").write_text("\n".join(lines) + "\n")


__all__ = ["add_parser", "run_trial", "sweep", "write_table"]
