"""The end of a training run: the env workers closed, then the policy and the curve written,
whenever Ctrl-C comes.

A Ctrl-C after the last update (``timeout -s INT`` a moment after the run finished, a user
pressing it as the bar reaches 100 %) used to land in the workers' close or in the export:
the run ended with exit 130, a checkpoint of every update and no ``policy.onnx``, the
interrupt message never printed (seen on the H200 host, 2026-11-28). Here a Ctrl-C while a
clean close waits on the workers ends them instead, and one while the last files are written
is noted and acted on once they are: the run ends as a Ctrl-C does, with the policy.

A second SIGINT close behind the first (``timeout`` signals the command and then its process
group, which holds the command again; a supervisor may do the same) used to land in the save
that the first one starts: exit 130, no ``policy.onnx`` and no word. After a Ctrl-C, another
within ``DUPLICATE_S`` is taken for a copy of it (``duplicates_ignored``). Whether this is
what cut avoid's DAgger on the H200 host short (2026-11-28: empty log, no policy, at the
``timeout -s INT``) is not shown: here coreutils 9.1 delivered one signal in 10 of 10 tries.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

DUPLICATE_S = 0.5
"""A SIGINT this soon after the Ctrl-C a run is ending on is a copy of it, not a second one
(``timeout``'s two signals arrive microseconds apart; a person's second press takes longer)."""


@contextlib.contextmanager
def duplicates_ignored() -> Iterator[None]:
    """Inside (entered as a Ctrl-C is caught): a SIGINT within ``DUPLICATE_S`` is ignored, a
    later one raises as usual, so a save that hangs can still be left. Where Ctrl-C is not
    Python's KeyboardInterrupt nothing changes (as ``interrupt_noted``)."""
    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGINT) if main else None
    if previous is not signal.default_int_handler:
        yield
        return
    caught = time.monotonic()

    def copy_or_second(signum: int, frame: Any) -> None:
        if time.monotonic() - caught > DUPLICATE_S:
            raise KeyboardInterrupt

    signal.signal(signal.SIGINT, copy_or_second)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def close_workers(close: Callable[[bool], None], interrupted: bool) -> bool:
    """``close(interrupted)``; a Ctrl-C while it waits on the workers ends them instead
    (``close(True)``), and so does a worker gone by the end (a broken pipe: what it sent
    before is in the run already). Whether the run was interrupted."""
    try:
        close(interrupted)
    except KeyboardInterrupt:
        if interrupted:
            raise  # a second Ctrl-C while the workers are being ended: give up on them
        with duplicates_ignored():
            close(True)
        return True
    except (OSError, EOFError) as exc:
        if interrupted:
            raise
        print(f"jetbot-train: an env worker was gone at the end ({exc or type(exc).__name__}); "
              "the others were ended", file=sys.stderr)
        close(True)
    return interrupted


@contextlib.contextmanager
def interrupt_noted() -> Iterator[Callable[[], bool]]:
    """A Ctrl-C inside is noted, not raised (the yielded function tells whether one came); a
    second raises as usual (one within ``DUPLICATE_S`` is the first's copy), so a write that
    hangs can still be left. Where Ctrl-C is not
    Python's KeyboardInterrupt (ignored in a background job, another handler, not the main
    thread) nothing changes."""
    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGINT) if main else None
    if previous is not signal.default_int_handler:
        yield lambda: False
        return
    received: list[float] = []

    def note(signum: int, frame: Any) -> None:
        if received and time.monotonic() - received[0] > DUPLICATE_S:
            raise KeyboardInterrupt
        received.append(time.monotonic())

    signal.signal(signal.SIGINT, note)
    try:
        yield lambda: bool(received)
    finally:
        signal.signal(signal.SIGINT, previous)
