"""The run's lifecycle: named phases entered in order, each released by its own ``exit`` in
reverse order, with the stop latch looked at between every two.

``Lifecycle`` is the driver. A phase is put on its exit stack *before* its ``enter`` runs, so a
phase that fails halfway still releases what it opened; ``unwind`` calls the exits last-in,
first-out and goes on past one that fails. Whatever a phase brings up that the stop must report
on (the drive, the robot's counters, the recorder) it hands to ``Shutdown`` instead.

A start-up step that may sit in native code for minutes runs in a worker thread
(``in_worker``) so that a stop request ends the start at once. Such a thread cannot be joined
or interrupted; ``exit_if_stuck`` is the one place that ends the process around it.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from typing import Callable, Iterable, TypeVar

from jetbot_rt.errors import first_line
from jetbot_rt.runtime.safety import SafeStopLatch
from jetbot_rt.service import console, signals

START_POLL_S = 0.02
"""How often the main thread looks at the latch while a start-up step runs in a worker."""

T = TypeVar("T")


class Cancelled(BaseException):
    """A stop request (signal, control socket) arrived during start-up. Not an ``Exception``:
    a phase's own ``except Exception`` must not take it for a failure of its step."""


class Phase:
    """One step of the start, named by its class. ``enter`` brings something up; ``exit``
    releases it, also after an ``enter`` that failed halfway (it looks at what was opened).
    ``exit`` should not raise: the driver says on stderr what did and goes on."""

    def enter(self) -> None:
        raise NotImplementedError

    def exit(self) -> None:
        """Most phases open nothing of their own: what they start, the robot stops."""


class Lifecycle:
    def __init__(self, latch: SafeStopLatch) -> None:
        self.latch = latch
        self.stuck: list[threading.Thread] = []
        """Threads left in native code (a load, a warm-up, a tick): the exit cannot join them."""
        self._entered: list[Phase] = []

    def run(self, phases: Iterable[Phase]) -> None:
        """Enter each phase in turn; a tripped latch between two ends the start (``Cancelled``)."""
        for phase in phases:
            self.check()
            self._entered.append(phase)
            phase.enter()

    def check(self) -> None:
        """For a phase with a long step inside it: end the start now if a stop was asked for,
        or if a signal's ``Interrupted`` was raised during the start and did not end it
        (``signals.raise_if_swallowed``; seen once under load: a SIGINT 0.15 s into ``run``
        lost, and the run drove its whole duration)."""
        if self.latch.tripped:
            raise Cancelled
        signals.raise_if_swallowed()

    def unwind(self) -> None:
        """Every entered phase's ``exit``, the last entered first; each phase at most once."""
        while self._entered:
            phase = self._entered.pop()
            try:
                phase.exit()
            except Exception as exc:  # cleanup must go on; say what failed
                print(f"jetbot-rt: cleanup: {first_line(exc)}", file=sys.stderr)

    def in_worker(self, what: str, target: Callable[[], T], limit: float) -> T:
        """Run a start-up step that may sit in native code for minutes (a model load, a
        TensorRT build, the first inference) in a worker thread, so that a stop request or a
        signal ends the start within ``START_POLL_S``, not when the step returns. Raises
        ``TimeoutError`` after ``limit`` s; the worker is then left running."""
        result: list[T] = []
        error: list[BaseException] = []

        def body() -> None:
            try:
                result.append(target())
            except BaseException as exc:
                error.append(exc)

        worker = threading.Thread(target=body, name=f"jetbot-rt-{what}", daemon=True)
        worker.start()
        deadline = time.monotonic() + limit
        while worker.is_alive():
            if self.latch.tripped:
                self.stuck.append(worker)
                raise Cancelled
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.stuck.append(worker)
                raise TimeoutError
            worker.join(min(remaining, START_POLL_S))
        if error:
            raise error[0]
        return result[0]

    def exit_if_stuck(self, exit_code: int, line: str | None = None) -> None:
        """End the process now with ``exit_code`` (after ``line`` on stderr) if a thread is
        stuck in native code; return otherwise. Call it once the motors are zero.

        Why not return: the interpreter's shutdown would wait on such a thread or abort
        (SIGABRT, "terminate called without an active exception"), and no Python code can
        interrupt it. ``os._exit`` skips that shutdown; the console gets its bounded drain
        first, so a stalled reader costs the last lines, not the exit."""
        if not any(thread.is_alive() for thread in self.stuck):
            return
        if line is not None:
            print(line, file=sys.stderr, flush=True)
        console.drain()
        os._exit(exit_code)
