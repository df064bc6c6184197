"""A training run's directory: what ``jetbot-train train`` writes and ``--resume`` reads.

``OUT/checkpoint.pt`` (``checkpoint.py``), ``policy.onnx`` (``export.py``), ``metrics.csv``
(one row per PPO update or DAgger iteration), ``learning_curve.png`` and, for PPO with the
``tensorboard`` extra, TensorBoard events. Both trainers and the sweep go through
``RunDirectory``: ``prepare`` (writable; the checkpoint to resume from, or a fresh start),
``append_metrics``, ``plot_curve``, ``save_checkpoint``, ``export_policy``, ``summary``,
``close``.

What is already in OUT is not trusted (a copied run, a shared directory, a file planted by
whoever else can write there):

- OUT itself must not be a symbolic link and must be owned by us or root (``out_dir``):
  the owner of a directory can plant a link at any name we are about to write, and root would
  write through it. It is opened once; every file after that is named relative to that
  descriptor (``/proc/self/fd/N/NAME``), so renaming OUT or a directory above it, or putting
  a link in its place, mid-run changes nothing about where the files go.
- Every file is created without following a link: whole files (checkpoint, policy, curve,
  the write test) with ``safe_file.replaced_file``/``create_new`` (``O_CREAT|O_EXCL|
  O_NOFOLLOW``, write-then-rename), and ``metrics.csv`` is appended to through one
  descriptor opened at the start with ``O_NOFOLLOW|O_NONBLOCK`` and checked to be a regular
  file of ours with no other hard link.
- On ``--resume``, ``metrics.csv`` is read once, through that descriptor, by ``safe_file``
  (at most ``MAX_METRICS_BYTES``, strict UTF-8) and validated before any training (the
  columns this trainer writes, numbers that are finite): a bad one is one line and exit 2,
  never a traceback after the training time is spent. The curve is drawn from the rows kept
  in memory, so nothing is read back later.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import math
import os
import stat
import time
import weakref
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import shown
from jetbot_rt.config.sections import Config
from jetbot_rt.errors import UsageError
from jetbot_rt.train.checkpoint import (
    CHECKPOINT_NAME,
    Checkpoint,
    TrainingState,
    load_checkpoint,
    save_checkpoint,
)
from jetbot_rt.train.device import to_cpu
from jetbot_rt.train.env import calibrated_robot
from jetbot_rt.train.export import export_model
from jetbot_rt.train.hyperparams import CriticConfig
from jetbot_rt.train.model import CRITIC, ActorCritic
from jetbot_rt.train.out_dir import inside, writable_directory

METRICS_NAME = "metrics.csv"
CURVE_NAME = "learning_curve.png"
POLICY_NAME = "policy.onnx"
RUN_FILES = (CHECKPOINT_NAME, POLICY_NAME, METRICS_NAME, CURVE_NAME)
MAX_METRICS_BYTES = 16 * safe_file.MIB
"""A PPO row is about 150 bytes: 16 MiB is 100,000 updates, 200 M steps at 2048 per update."""
STEP_COLUMN = "global_step"
MAX_STEP_DIGITS = 19
"""A step count longer than this is not one (2**63 has 19 digits), and Python before 3.11
converts a long digit string in quadratic time."""

Value = float | None
"""A metrics cell: a number, or None where the row has no value (no episode ended yet)."""


class Interrupted(Exception):
    """Ctrl-C during training; the checkpoint, curve and policy were written."""

    def __init__(self, summary: dict[str, Any]) -> None:
        super().__init__("interrupted")
        self.summary = summary


@contextlib.contextmanager
def _named(where: Path, display: Path) -> Iterator[None]:
    """A ``UsageError`` names the file as the user gave it, not as ``/proc`` does."""
    try:
        yield
    except UsageError as exc:
        raise UsageError(str(exc).replace(str(where), shown(display))) from None


def _clip(text: str, limit: int = 60) -> str:
    return repr(text if len(text) <= limit else text[:limit] + "...")


def parse_metrics(text: str, names: tuple[str, ...], display: Path
                  ) -> tuple[bool, list[tuple[Value, ...]]]:
    """Whether ``text`` (a ``metrics.csv``) has its header, and its rows as numbers: the
    header must be ``names`` (the columns this trainer writes), each row as many cells, each
    cell empty or a finite number, ``global_step`` a whole number >= 0. Else ``UsageError``."""
    def bad(line: int, problem: str) -> UsageError:
        return UsageError(f"{shown(display)} line {line}: {problem} (not a metrics file this "
                          "trainer wrote; move it away to resume without it)")

    reader = csv.reader(io.StringIO(text, newline=""))
    rows: list[tuple[Value, ...]] = []
    try:
        header = next(reader, None)
        if header is None:
            return False, rows
        if tuple(header) != names:
            extra = [name for name in header if name not in names][:3]
            lacks = [name for name in names if name not in header][:3]
            detail = "".join(f"; {what} {_clip(', '.join(those), 40)}" for what, those
                             in (("it has", extra), ("it lacks", lacks)) if those)
            # a column some options add (--target-kl's epochs, --curriculum's difficulty,
            # --predict-state's state_loss): the run was started with other options
            raise UsageError(f"{shown(display)} line 1: the columns are "
                             f"{_clip(','.join(header))}, expected {_clip(','.join(names))}"
                             f"{detail} (a run started with other options, such as "
                             "--target-kl, --curriculum or --predict-state: resume with "
                             "those; or not a metrics file this trainer wrote: move it away)")
        for cells in reader:
            if not cells:
                continue
            if len(cells) != len(names):
                raise bad(reader.line_num, f"{len(cells)} cells, expected {len(names)}")
            try:
                rows.append(tuple(_cell(name, cell)
                                  for name, cell in zip(names, cells, strict=True)))
            except ValueError as exc:
                raise bad(reader.line_num, str(exc)) from None
    except csv.Error as exc:
        raise bad(reader.line_num, str(exc)) from None
    return True, rows


def _cell(name: str, cell: str) -> Value:
    if cell == "":
        return None
    if name == STEP_COLUMN:
        if not (cell.isascii() and cell.isdigit() and len(cell) <= MAX_STEP_DIGITS):
            raise ValueError(f"{name} {_clip(cell)} is not a step count")
        return float(int(cell))
    try:
        value = float(cell)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise ValueError(f"{name} {_clip(cell)} is not a finite number")
    return value


def starting_model(options: Any, saved: Checkpoint | None, algo: str,
                   critic: CriticConfig | None = None
                   ) -> tuple[ActorCritic, TrainingState | None]:
    """The network a run of ``algo`` with ``critic`` (PPO's asymmetric one, else None) starts
    from, and the training state it resumes (None for a new run): fresh (``options.model``),
    then ``options.init``'s, then ``saved``'s. Each is built in turn, as they draw from
    torch's generator in this order. ``init`` gives its network's actor always and its
    critic only where it is the one asked for (else a fresh critic, or none); ``saved`` must
    have the critic asked for (``Checkpoint.check_resumable``)."""
    model = ActorCritic(options.model, critic)
    if options.init:
        model = _with_critic(load_checkpoint(options.init).model(), critic)
    if saved is None:
        return model, None
    resumed = saved.check_resumable(options.task, algo, critic)
    return saved.model(), resumed


def _with_critic(model: ActorCritic, critic: CriticConfig | None) -> ActorCritic:
    """``model``'s actor with ``critic``: ``model`` itself where its critic is of that kind
    and width, else a network with a fresh critic (or none) and ``model``'s actor weights."""
    have = model.critic_config
    if have is None and critic is None:
        return model
    kept = model.actor_state_dict()
    if have is not None and critic is not None and have.state_size == critic.state_size:
        if have.predicts_state == critic.predicts_state:
            return model
        # the critic kept as trained (its width too), a state head added or dropped
        critic = replace(have, predicts_state=critic.predicts_state)
        kept.update({name: weight for name, weight in model.state_dict().items()
                     if name.startswith(CRITIC + ".")})
    fresh = ActorCritic(model.config, critic)
    fresh.load_state_dict(kept, strict=False)
    return fresh.eval()


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


def _close_all(fds: dict[str, int]) -> None:
    for fd in fds.values():
        with contextlib.suppress(OSError):
            os.close(fd)
    fds.clear()


class RunDirectory:
    def __init__(self, path: str | Path, names: tuple[str, ...]) -> None:
        """``names``: the metrics columns of this trainer."""
        self.path = Path(path)
        self.names = names
        self.checkpoint = self.path / CHECKPOINT_NAME
        self.metrics = self.path / METRICS_NAME
        self.curve = self.path / CURVE_NAME
        self.policy = self.path / POLICY_NAME
        self.rows: list[tuple[Value, ...]] = []
        """Every row of ``metrics.csv``: those read on resume, then those appended."""
        self._header = False
        self._fds: dict[str, int] = {}
        """``dir`` and ``metrics`` once open; closed by ``close`` (or when collected)."""
        self.close = weakref.finalize(self, _close_all, self._fds)

    def inside(self, name: str = "") -> Path:
        """Where ``name`` in the directory opened by ``prepare`` is, for a library that
        writes files of its own there (TensorBoard)."""
        return inside(self._fds["dir"], name)

    def prepare(self, resume: bool, check: Callable[[Checkpoint], object] | None = None
                ) -> Checkpoint | None:
        """The checkpoint to continue from when ``resume`` finds one (and the metrics so
        far, checked); else a fresh start (the metrics of an earlier run are removed).
        ``check`` raises for a checkpoint this run cannot continue, before the metrics are
        read (whose columns such a run's may not match)."""
        try:
            self._fds["dir"] = writable_directory(self.path)
            if resume and self._exists(CHECKPOINT_NAME):
                saved = load_checkpoint(self.inside(CHECKPOINT_NAME), follow_links=False,
                                        label=self.checkpoint)
                if check is not None:
                    check(saved)
                self._read_metrics()
                return saved
            self._remove(METRICS_NAME)
            return None
        except BaseException:
            self.close()
            raise

    def _exists(self, name: str) -> bool:
        try:
            os.stat(name, dir_fd=self._fds["dir"], follow_symlinks=False)
        except FileNotFoundError:
            return False
        return True

    def _remove(self, name: str) -> None:
        try:
            os.unlink(name, dir_fd=self._fds["dir"])
        except FileNotFoundError:
            pass
        except OSError as exc:
            raise UsageError(f"cannot remove {shown(self.path / name)}: "
                             f"{exc.strerror or exc}") from None

    def _read_metrics(self) -> None:
        """Open ``metrics.csv`` for the appends to come and read what it holds."""
        flags = (os.O_RDWR | os.O_APPEND | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY
                 | os.O_CLOEXEC)
        try:
            fd = os.open(METRICS_NAME, flags, dir_fd=self._fds["dir"])
        except FileNotFoundError:
            return  # the first append creates it
        except OSError as exc:
            reason = ("a symbolic link (not followed here)" if exc.errno == errno.ELOOP
                      else exc.strerror or str(exc))
            raise UsageError(f"cannot open {shown(self.metrics)}: {reason}") from None
        self._fds["metrics"] = fd
        info, me = os.fstat(fd), os.geteuid()
        problem = ("not a regular file" if not stat.S_ISREG(info.st_mode)
                   else f"owned by uid {info.st_uid}, not by you (uid {me})"
                   if info.st_uid != me
                   else "it has other hard links" if info.st_nlink != 1 else None)
        if problem is not None:
            raise UsageError(f"{shown(self.metrics)}: {problem}; move it away to resume "
                             "without it")
        os.set_blocking(fd, True)
        with _named(inside(fd), self.metrics):
            data = safe_file.read_bytes(inside(fd), "metrics file", MAX_METRICS_BYTES)
        text = safe_file.decode(data, self.metrics, "metrics file")
        self._header, self.rows = parse_metrics(text, self.names, self.metrics)

    def append_metrics(self, row: dict[str, Any]) -> None:
        """One row more in ``metrics.csv`` (created now if it is not there yet)."""
        values = [row.get(name, "") for name in self.names]
        buffer = io.StringIO(newline="")
        writer = csv.writer(buffer)
        try:
            if "metrics" not in self._fds:
                self._fds["metrics"] = safe_file.create_new(self.inside(METRICS_NAME))
            if not self._header:
                writer.writerow(self.names)
            writer.writerow(values)
            data = buffer.getvalue().encode()
            while data:
                data = data[os.write(self._fds["metrics"], data):]
        except OSError as exc:
            raise UsageError(f"cannot write {shown(self.metrics)}: {exc.strerror or exc}"
                             ) from None
        self._header = True
        self.rows.append(tuple(None if v == "" else float(v) for v in values))

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
            "calibrated": calibrated_robot(options.config, options.task),
            "args": {k: v for k, v in asdict(options).items() if k not in ("config", "model")},
        }
        if reward_rms is not None:
            state["reward_rms"] = reward_rms
        if model.critic_config is not None:
            state["critic"] = model.critic_config.to_dict()
        save_checkpoint(self.inside(CHECKPOINT_NAME), state)

    def export_policy(self, model: ActorCritic, task: str, max_speed: float, config: Config,
                      name: str = POLICY_NAME) -> None:
        """``config``: the run's; a policy trained on a calibrated robot (``[randomize]
        deadband_lift``) says it expects the lift."""
        with _named(self.inside(), self.path):
            export_model(model, self.inside(name), task=task, max_speed=max_speed,
                         calibrated=calibrated_robot(config, task))

    def plot_curve(self, title: str, panels: tuple[Panel, ...]) -> None:
        """``learning_curve.png``: each panel's column over the environment steps, from the
        rows that have a value in it (none yet: an empty plot that says so)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        step = self.names.index(STEP_COLUMN)
        fig, axes = plt.subplots(len(panels), 1, figsize=(7, 6), sharex=True)
        for ax, panel in zip(axes, panels, strict=True):
            column = self.names.index(panel.column)
            shown_rows = [r for r in self.rows if r[column] is not None and r[step] is not None]
            ax.plot([r[step] for r in shown_rows], [r[column] for r in shown_rows], panel.style,
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
        try:
            with safe_file.replaced_file(self.inside(), CURVE_NAME) as fd, \
                    os.fdopen(os.dup(fd), "wb") as handle:
                fig.savefig(handle, format="png", dpi=100)
        except OSError as exc:
            raise UsageError(f"cannot write {shown(self.curve)}: {exc.strerror or exc}"
                             ) from None
        finally:
            plt.close(fig)

    def summary(self, progress: Progress, steps_per_s: float | None) -> dict[str, Any]:
        return {"global_step": progress.global_step, "updates": progress.update,
                "wall_s": progress.wall_s(), "steps_per_s": steps_per_s,
                "checkpoint": str(self.checkpoint), "policy": str(self.policy)}
