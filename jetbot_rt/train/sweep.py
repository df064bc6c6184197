"""``jetbot-train sweep``: several seeds (and configs, e.g. randomization ranges) trained at once
across a Ray cluster, one table of results at the end.

A trial is one ordinary ``train`` run (its envs in ``num_envs`` processes on the node it
lands on, so it asks Ray for that many CPUs; one env runs in the trial's own process),
then ``evaluate`` of its policy on the task's evaluation episodes under the trial's config.
The trial's files (checkpoint, ONNX, metrics, curve) come back to the driver through Ray, so
the nodes need no shared disk: ``OUT/<trial>/``. ``OUT/sweep.csv`` and ``OUT/sweep.md`` hold
the table, which is also printed. A trial whose node dies is run again from the start
elsewhere (Ray's task retries).

OUT and each ``OUT/<trial>/`` are checked as a run directory is (``run_dir.own_directory``:
no symbolic link, ours or root's) and every file is written with ``safe_file.replaced_file``
relative to the directory opened once: a link planted at a name is replaced, never followed.
"""

from __future__ import annotations

import csv
import io
import os
import tempfile
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from jetbot_rt.config import safe_file
from jetbot_rt.errors import UsageError
from jetbot_rt.train.hyperparams import OptionError, PPOArgs, ppo_args, read_config_file
from jetbot_rt.train.out_dir import inside, own_directory, writable_directory
from jetbot_rt.train.run_dir import METRICS_NAME, RUN_FILES

COLUMNS = ("trial", "config", "seed", "eval_success_rate", "eval_mean_return",
           "train_success_rate", "global_step", "steps_per_s", "wall_s", "node")


def run_trial(name: str, options: PPOArgs, config_name: str,
              eval_episodes: int) -> dict[str, Any]:
    """One trial on whichever node Ray chose: train, evaluate, hand the files back."""
    import ray

    from jetbot_rt.train.evaluate import evaluate
    from jetbot_rt.train.ppo import train

    with tempfile.TemporaryDirectory(prefix=f"jetbot-sweep-{name}-") as out:
        summary = train(replace(options, out=out))
        result = evaluate(summary["policy"], task=options.task, episodes=eval_episodes,
                          num_workers=options.num_envs, config=options.config)
        with (Path(out) / METRICS_NAME).open() as handle:
            last = list(csv.DictReader(handle))[-1]
        files = {f: (Path(out) / f).read_bytes() for f in RUN_FILES if (Path(out) / f).exists()}
    row = {
        "trial": name, "config": config_name, "seed": options.seed,
        "eval_success_rate": result["success_rate"],
        "eval_mean_return": round(float(result["mean_return"]), 1),
        "train_success_rate": last.get("success_rate", ""),
        "global_step": summary["global_step"], "steps_per_s": summary["steps_per_s"],
        "wall_s": round(summary["wall_s"], 1),
        "node": ray.get_runtime_context().get_node_id()[:8],
    }
    return {"row": row, "files": files}


def trial_options(task: str, seeds: Sequence[int], configs: Sequence[str | None],
                  num_envs: int, timesteps: int | None) -> list[tuple[str, str, PPOArgs]]:
    """(trial name, config name, its ``PPOArgs``) for every config and seed: the task's PPO
    defaults, the config's ``[train]`` table, then the sweep's own settings."""
    named = [(Path(p).stem if p else "default", *read_config_file(p)) for p in configs]
    if len({name for name, _, _ in named}) != len(named):
        raise OptionError("config", "files must have different names (they name the trials)")
    trials = []
    for config_name, config, table in named:
        for seed in seeds:
            settings = {**table, "num_envs": num_envs, "seed": seed,
                        "workers": 0 if num_envs == 1 else None, "ray": None,
                        "progress": False, "update_threads": num_envs,
                        "device": "cpu"}  # Ray gives a trial CPUs, not a GPU
            if timesteps is not None:
                settings["total_timesteps"] = timesteps
            options = ppo_args(task, settings)
            options.config = config
            trials.append((f"{config_name}-seed{seed}", config_name, options))
    return trials


def sweep(task: str, out: str | Path, *, seeds: Sequence[int] = (1, 2, 3),
          configs: Sequence[str | None] = (None,), num_envs: int = 2,
          timesteps: int | None = None, eval_episodes: int = 20,
          ray_address: str = "local") -> list[dict[str, Any]]:
    """Train a trial per config (TOML files; None: the built-in config) and seed on the Ray
    cluster at ``ray_address``, ``num_envs`` CPUs each; evaluate each policy on
    ``eval_episodes`` episodes; the files to ``out/<trial>/``, the table to ``out/sweep.csv``
    and ``out/sweep.md``. Returns the table's rows."""
    for name, value in (("timesteps", timesteps), ("num_envs", num_envs),
                        ("eval_episodes", eval_episodes)):
        if value is not None and value <= 0:
            raise OptionError(name, f"must be > 0, got {value}")
    out = Path(out)
    out_fd = writable_directory(out)
    try:
        rows = _run_trials(task, out, out_fd, seeds, configs, num_envs, timesteps,
                           eval_episodes, ray_address)
    finally:
        os.close(out_fd)
    return rows


def _run_trials(task: str, out: Path, out_fd: int, seeds: Sequence[int],
                configs: Sequence[str | None], num_envs: int, timesteps: int | None,
                eval_episodes: int, ray_address: str) -> list[dict[str, Any]]:
    trials = trial_options(task, seeds, configs, num_envs, timesteps)
    from jetbot_rt.train.ray_workers import connect  # imports ray

    owns = connect(ray_address)
    import ray

    refs: list[Any] = []
    try:
        remote = ray.remote(num_cpus=num_envs, max_retries=2)(run_trial)
        refs = [remote.remote(name, options, config_name, eval_episodes)
                for name, config_name, options in trials]
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
        trial_fd = own_directory(row["trial"], "trial directory", parent=out_fd,
                                 display=out / row["trial"])
        try:
            for file_name, data in result["files"].items():
                _write(trial_fd, file_name, data, out / row["trial"])
        finally:
            os.close(trial_fd)
        rows.append(row)
    write_table(rows, out_fd, out)
    return rows


def _write(dir_fd: int, name: str, data: bytes, display: Path) -> None:
    """``data`` as ``name`` in the directory open as ``dir_fd``, never through a link."""
    try:
        with safe_file.replaced_file(inside(dir_fd), name) as fd:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
    except OSError as exc:
        raise UsageError(f"cannot write {safe_file.shown(display / name)}: "
                         f"{exc.strerror or exc}") from None


def markdown_table(rows: list[dict[str, Any]]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + " --- |" * len(COLUMNS)]
    lines += ["| " + " | ".join(str(row[c]) for c in COLUMNS) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def write_table(rows: list[dict[str, Any]], out_fd: int, out: Path) -> None:
    """``sweep.csv`` and ``sweep.md`` in the directory open as ``out_fd`` (``out``)."""
    buffer = io.StringIO(newline="")
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    _write(out_fd, "sweep.csv", buffer.getvalue().encode(), out)
    _write(out_fd, "sweep.md", markdown_table(rows).encode(), out)
