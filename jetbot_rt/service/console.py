"""stdout and stderr that never block the caller: a pipe nobody reads, a terminal stopped with
Ctrl-S or a stalled journald costs output, never a tick, a stop or the exit.

``unblocked()`` replaces ``sys.stdout`` and ``sys.stderr`` (only the interpreter's own: a
stream someone else put there, a test's capture, is left alone) with ``NonBlockingStream``s.
A write encodes the text and hands it to a queue (``queue.SimpleQueue``, whose ``put`` takes no
lock a caller could wait on and is safe even from a signal handler) and returns; one writer
thread per stream writes the queue to a duplicate of the stream's descriptor, and only that
thread can block. More than ``QUEUE_BYTES`` waiting is dropped and counted. ``flush()`` returns
at once; ``drain(timeout)`` waits a bounded time (the exit path: ``unblocked``'s end, a run's
``os._exit``). Writes of the C libraries straight to the descriptors are not covered.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import queue
import select
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

QUEUE_BYTES = 1 << 20
"""Output waiting for a stalled reader before more is dropped (many times a run's output)."""
DRAIN_S = 0.5
"""How long the exit waits for the writers to hand their queues to the descriptors."""
_POLL_S = 0.005


class NonBlockingStream:
    """A text stream (``write``, ``flush``, ``fileno``, ``isatty``...) over a writer thread."""

    def __init__(self, original: Any, limit: int = QUEUE_BYTES) -> None:
        self.original = original
        self.encoding: str = original.encoding
        # A text that cannot be encoded is written escaped: a print must not raise on the exit path.
        errors = original.errors or "strict"
        self.errors: str = "backslashreplace" if errors == "strict" else errors
        self._fd = os.dup(original.fileno())  # its own: a dup2 onto fd 1/2 does not redirect it
        self._limit = limit
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._queued = 0  # bytes, counted by the callers
        self._written = 0  # bytes taken off the queue, counted by the writer alone
        self.lost = 0
        """Bytes dropped: the queue was full, the reader had gone, or the exit could not wait."""
        self.error: str | None = None
        self._writer = threading.Thread(target=self._write_all, daemon=True,
                                        name=f"jetbot-rt-{original.name.strip('<>')}")
        self._writer.start()

    # ---- the text stream interface -----------------------------------------------------

    def write(self, text: str) -> int:
        data = text.encode(self.encoding, self.errors)
        if self.error is not None or self._queued - self._written + len(data) > self._limit:
            self.lost += len(data)
        elif data:
            self._queued += len(data)
            self._queue.put(data)
        return len(text)

    def writelines(self, lines: Any) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        """Returns at once: the writer writes as soon as the descriptor takes it."""

    def fileno(self) -> int:
        return int(self.original.fileno())

    def isatty(self) -> bool:
        return bool(self.original.isatty())

    def writable(self) -> bool:
        return True

    def readable(self) -> bool:
        return False

    @property
    def closed(self) -> bool:
        return False

    @property
    def name(self) -> str:
        return str(self.original.name)

    # ---- the exit path -----------------------------------------------------------------

    def drain(self, timeout: float) -> bool:
        """Wait at most ``timeout`` s for everything queued so far to be written; True if it
        was. What is still queued after that is counted as lost."""
        return self.drained(self.mark(), timeout)

    def mark(self) -> threading.Event:
        """An event the writer sets once everything queued before it is written."""
        done = threading.Event()
        self._queue.put(done)
        return done

    def drained(self, mark: threading.Event, timeout: float) -> bool:
        if mark.wait(timeout):
            return self.error is None
        self.lost += max(0, self._queued - self._written)
        return False

    def close(self) -> None:
        """The writer closes its descriptor once it has written what is queued (if ever)."""
        self._queue.put(None)

    # ---- the writer thread -------------------------------------------------------------

    def _write_all(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                os.close(self._fd)
                return
            if isinstance(item, threading.Event):
                item.set()
                continue
            self._written += len(item)
            if self.error is not None:
                self.lost += len(item)
                continue
            try:
                self._write_one(item)
            except OSError as exc:  # the reader went away (EPIPE), a device error
                self.error = exc.strerror or str(exc)
                self.lost += len(item)

    def _write_one(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                written = os.write(self._fd, view)
            except BlockingIOError:  # someone made the descriptor non-blocking: wait for room
                select.select([], [self._fd], [], 0.05)
                continue
            view = view[written:]


def _replaceable(name: str) -> Any:
    """``sys.<name>`` if it is still the interpreter's own stream on a descriptor, else None."""
    current = getattr(sys, name)
    if current is None or current is not getattr(sys, f"__{name}__"):
        return None
    try:
        current.fileno()
    except (OSError, ValueError, AttributeError):
        return None
    return current


@contextlib.contextmanager
def unblocked(enabled: bool = True, drain_s: float = DRAIN_S) -> Iterator[None]:
    """``sys.stdout`` and ``sys.stderr`` as ``NonBlockingStream``s inside; at the end the
    writers get at most ``drain_s`` together, what stdout lost is said on stderr, and the
    original streams are back."""
    installed: dict[str, NonBlockingStream] = {}
    if enabled:
        for name in ("stdout", "stderr"):
            original = _replaceable(name)
            if original is not None:
                original.flush()  # nothing is written yet: this makes no system call
                installed[name] = NonBlockingStream(original)
                setattr(sys, name, installed[name])
    try:
        yield
    except BaseException as exc:
        if installed and not isinstance(exc, SystemExit):
            # A bug's traceback, printed by the interpreter after this, must not block the
            # exit either: the streams stay, and the exit gives them their bounded drain.
            atexit.register(drain, drain_s)
            installed.clear()
        raise
    finally:
        if installed:
            drain(drain_s)
            out, err = installed.get("stdout"), installed.get("stderr")
            if out is not None and out.lost:
                why = out.error or "nobody read them"
                print(f"jetbot-rt: stdout: {out.lost} bytes not written ({why})", file=sys.stderr)
                if err is not None:
                    err.drain(drain_s / 2)
            for name, stream in installed.items():
                setattr(sys, name, stream.original)
                stream.close()


def drain(timeout: float = DRAIN_S) -> None:
    """Before the process ends (``os._exit`` included): the non-blocking streams get at most
    ``timeout`` s together to write what they hold; other streams are flushed as they are."""
    deadline = time.monotonic() + timeout
    marks = []
    for stream in (sys.stdout, sys.stderr):
        if isinstance(stream, NonBlockingStream):
            marks.append((stream, stream.mark()))  # both writers at work at once
        elif stream is not None:
            with contextlib.suppress(OSError, ValueError):
                stream.flush()
    for stream, mark in marks:
        stream.drained(mark, max(0.0, deadline - time.monotonic()))
