"""A training run's directory: what ``jetbot-train train`` writes and ``--resume`` reads.

``OUT/checkpoint.pt`` (``checkpoint.py``), ``policy.onnx`` (``export.py``), ``metrics.csv``
(one row per PPO update or DAgger iteration), ``learning_curve.png`` and, for PPO with the
``tensorboard`` extra, TensorBoard events. Both trainers and the sweep go through
``RunDirectory``: ``prepare`` (writable; the checkpoint to resume from, or a fresh start),
``append_metrics``, ``plot_curve``, ``save_checkpoint``, ``export_policy``, ``summary``.
"""

from __future__ import annotations

import csv
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from jetbot_rt.config.safe_file import shown
from jetbot_rt.errors import UsageError
from jetbot_rt.train.checkpoint import (
    CHECKPOINT_NAME,
    Checkpoint,
    TrainingState,
    load_checkpoint,
    save_checkpoint,
)
from jetbot_rt.train.device import to_cpu
from jetbot_rt.train.export import export_model
from jetbot_rt.train.model import ActorCritic

METRICS_NAME = "metrics.csv"
CURVE_NAME = "learning_curve.png"
POLICY_NAME = "policy.onnx"
RUN_FILES = (CHECKPOINT_NAME, POLICY_NAME, METRICS_NAME, CURVE_NAME)


class Interrupted(Exception):
    """Ctrl-C during training; the checkpoint, curve and policy were written."""

    def __init__(self, summary: dict[str, Any]) -> None:
        super().__init__("interrupted")
        self.summary = summary


def writable_directory(path: Path) -> None:
    """Create ``path`` if needed and make sure a file can be written in it, before any work
    that would be lost."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".write_test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UsageError(f"cannot write to output directory {shown(path)}: "
                         f"{exc.strerror or exc}") from None


def starting_model(options: Any, saved: Checkpoint | None, algo: str
                   ) -> tuple[ActorCritic, TrainingState | None]:
    """The network a run of ``algo`` starts from, and the training state it resumes (None for
    a new run): fresh (``options.model``), then ``options.init``'s, then ``saved``'s. Each is
    built in turn, as they draw from torch's generator in this order."""
    model = ActorCritic(options.model)
    if options.init:
        model = load_checkpoint(options.init).model()
    if saved is None:
        return model, None
    resumed = saved.check_resumable(options.task, algo)
    return saved.model(), resumed


@dataclass
class Progress:
    """Where a run stands. The counters move only when an update (an iteration) finishes, so
    a checkpoint written at any moment describes finished work."""

    global_step: int = 0
    update: int = 0
    """PPO updates or DAgger iterations finished, over all runs of this directory."""
    wall_before: float = 0.0
    """Seconds the earlier runs of this directory took."""
    started: float = field(default_factory=time.perf_counter)
    start_step: int = 0
    """``global_step`` when this run started."""

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def wall_s(self) -> float:
        return self.wall_before + self.elapsed()


@dataclass(frozen=True)
class Panel:
    """One plot of the learning curve: a metrics column over the environment steps."""

    column: str
    ylabel: str
    scale: tuple[str, dict[str, Any]] | None = None
    ylim: tuple[float, float] | None = None
    style: str = "-"
    color: str | None = None
    label: str | None = None


class RunDirectory:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.checkpoint = self.path / CHECKPOINT_NAME
        self.metrics = self.path / METRICS_NAME
        self.curve = self.path / CURVE_NAME
        self.policy = self.path / POLICY_NAME

    def prepare(self, resume: bool) -> Checkpoint | None:
        """The checkpoint to continue from when ``resume`` finds one; else a fresh start (the
        metrics of an earlier run are removed)."""
        writable_directory(self.path)
        if resume and self.checkpoint.exists():
            return load_checkpoint(self.checkpoint)
        self.metrics.unlink(missing_ok=True)
        return None

    def append_metrics(self, row: dict[str, Any], names: tuple[str, ...]) -> None:
        new = not self.metrics.exists()
        with self.metrics.open("a", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=names)
            if new:
                writer.writeheader()
            writer.writerow({k: row.get(k, "") for k in names})

    def save_checkpoint(self, *, algo: str, options: Any, model: ActorCritic,
                        optimizer: torch.optim.Optimizer, progress: Progress, max_speed: float,
                        reward_rms: dict[str, float] | None = None) -> None:
        """The model and optimizer with the progress (``options``: the run's ``PPOArgs`` or
        ``DAggerArgs``, kept as a record)."""
        state = {
            "task": options.task,
            "algo": algo,
            "model": to_cpu(model.state_dict()),
            "model_config": model.config.to_dict(),
            "optimizer": to_cpu(optimizer.state_dict()),
            "global_step": progress.global_step,
            "update": progress.update,
            "wall_s": progress.wall_s(),
            "max_speed": max_speed,
            "args": {k: v for k, v in asdict(options).items() if k not in ("config", "model")},
        }
        if reward_rms is not None:
            state["reward_rms"] = reward_rms
        save_checkpoint(self.checkpoint, state)

    def export_policy(self, model: ActorCritic, task: str, max_speed: float,
                      name: str = POLICY_NAME) -> None:
        export_model(model, self.path / name, task=task, max_speed=max_speed)

    def plot_curve(self, title: str, panels: tuple[Panel, ...]) -> None:
        """``learning_curve.png``: each panel's column over the environment steps, from the
        rows that have a value in it (none yet: an empty plot that says so)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        rows: list[dict[str, str]] = []
        if self.metrics.exists():  # not before the first update ends
            with self.metrics.open() as handle:
                rows = list(csv.DictReader(handle))
        fig, axes = plt.subplots(len(panels), 1, figsize=(7, 6), sharex=True)
        for ax, panel in zip(axes, panels, strict=True):
            shown_rows = [r for r in rows if r[panel.column]]
            ax.plot([int(r["global_step"]) for r in shown_rows],
                    [float(r[panel.column]) for r in shown_rows], panel.style,
                    color=panel.color, label=panel.label)
            if not shown_rows:
                ax.text(0.5, 0.5, "no data yet", ha="center", transform=ax.transAxes)
            elif panel.scale is not None:
                ax.set_yscale(panel.scale[0], **panel.scale[1])
            if panel.ylim is not None:
                ax.set_ylim(*panel.ylim)
            if panel.label is not None:
                ax.legend(loc="lower right")
            ax.set_ylabel(panel.ylabel)
        axes[-1].set_xlabel("environment steps")
        fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(self.curve, dpi=100)
        plt.close(fig)

    def summary(self, progress: Progress, steps_per_s: float | None) -> dict[str, Any]:
        return {"global_step": progress.global_step, "updates": progress.update,
                "wall_s": progress.wall_s(), "steps_per_s": steps_per_s,
                "checkpoint": str(self.checkpoint), "policy": str(self.policy)}
