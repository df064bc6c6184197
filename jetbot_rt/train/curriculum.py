"""Curricula: a task's difficulty raised during training as the student succeeds.

A task whose ``scene`` reads ``Task.difficulty`` (0: the easiest scenes .. 1: the task as it
is evaluated) says so with ``curriculum = True`` (seek: the goal nearer, fewer distractors).
With ``--curriculum`` the trainer starts at ``--curriculum-start`` and, each time the success
rate over the last ``--curriculum-window`` episodes finished at the current difficulty reaches
``--curriculum-threshold``, raises it by ``--curriculum-step``, never past 1 and never back.
The episodes are counted afresh after a raise. PPO counts every finished episode of its
rollouts, DAgger the episodes its student drove (the expert's say nothing about the student).

The difficulty reaches the env workers through the vector env's ``set_attr("difficulty",
d)``, which ``AsyncVectorEnv`` (a message down each worker's pipe), ``SyncVectorEnv`` and the
Ray workers (``RayVectorEnv.set_attr``, replayed to a restarted actor) pass to every env's
``JetbotEnv.difficulty``; it applies from each env's next reset. An episode running when the
difficulty rises finishes at the old one and is counted at the new one (at most one per env).

Evaluation is always at difficulty 1: its envs are built afresh, and an env's difficulty is
its own (``JetbotEnv`` copies the task before changing it). docs/CURRICULUM.md is the guide.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from typing import Any

from jetbot_rt.train.hyperparams import CurriculumOptions
from jetbot_rt.train.run_dir import Panel

COLUMN = "difficulty"
"""The metrics.csv column a run with a curriculum adds (after the trainer's own)."""


class Schedule:
    """The difficulty and the successes counted at it."""

    def __init__(self, start: float, threshold: float, window: int, step: float) -> None:
        self.difficulty = min(1.0, max(0.0, float(start)))
        self.threshold = threshold
        self.step = step
        self.recent: deque[float] = deque(maxlen=window)

    @classmethod
    def of(cls, options: CurriculumOptions, run: Any = None, resumed: bool = False,
           update: int = 0) -> Schedule | None:
        """The schedule ``options`` ask for (None without ``curriculum``): at
        ``curriculum_start``, or when ``resumed`` at the difficulty of the run directory
        ``run``'s metrics row of ``update`` (the checkpoint's)."""
        if not options.curriculum:
            return None
        difficulty = resumed_difficulty(run.rows, run.names, update) if resumed else None
        start = options.curriculum_start if difficulty is None else difficulty
        return cls(start, options.curriculum_threshold, options.curriculum_window,
                   options.curriculum_step)

    def rate(self) -> float | None:
        """The success rate over the window so far (None before any episode)."""
        return sum(self.recent) / len(self.recent) if self.recent else None

    def add(self, successes: Iterable[float]) -> bool:
        """Count finished episodes (1 success, 0 not); whether the difficulty rose."""
        for success in successes:
            self.recent.append(float(success))
        rate = self.rate()
        if (self.difficulty >= 1.0 or len(self.recent) < (self.recent.maxlen or 0)
                or rate is None or rate < self.threshold):
            return False
        self.difficulty = min(1.0, round(self.difficulty + self.step, 6))
        self.recent.clear()
        return True

    def after(self, row: dict[str, Any], successes: Iterable[float], envs: Any) -> None:
        """An update's bookkeeping: the difficulty its episodes were collected at into its
        metrics ``row``, its finished episodes counted, a raised difficulty sent to ``envs``."""
        row[COLUMN] = self.difficulty
        if self.add(successes):
            send(envs, self.difficulty)


def send(envs: Any, difficulty: float) -> None:
    """Set every env's difficulty (in its worker process, if it has one)."""
    envs.unwrapped.set_attr(COLUMN, difficulty)


def resumed_difficulty(rows: list[tuple[float | None, ...]], names: tuple[str, ...],
                       update: int) -> float | None:
    """The difficulty a resumed run continues at: the metrics row of the checkpoint's update
    (``names[0]``: the update / iteration column), else the last row with one; None if no row
    has a difficulty (a run without a curriculum)."""
    if COLUMN not in names:
        return None
    column = names.index(COLUMN)
    kept = [row for row in rows if row[column] is not None]
    at_checkpoint = [row for row in kept if row[0] == update]
    chosen = at_checkpoint[-1] if at_checkpoint else kept[-1] if kept else None
    return None if chosen is None else float(chosen[column])  # type: ignore[arg-type]


def curve(panels: tuple[Panel, ...], schedule: Schedule | None) -> tuple[Panel, ...]:
    """A trainer's learning-curve panels, with the difficulty's below them where there is a
    curriculum."""
    if schedule is None:
        return panels
    return (*panels, Panel(COLUMN, "difficulty (curriculum)", ylim=(-0.05, 1.05),
                           style="-", color="tab:purple"))


def metric_fields(fields: tuple[str, ...], options: CurriculumOptions) -> tuple[str, ...]:
    """A trainer's metrics columns, with the difficulty's where there is a curriculum (a run
    without one writes the columns it always did, so its directory resumes as before)."""
    return (*fields, COLUMN) if options.curriculum else fields


__all__ = ["COLUMN", "Schedule", "curve", "metric_fields", "resumed_difficulty", "send"]
