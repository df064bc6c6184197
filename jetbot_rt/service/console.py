"""stdout and stderr that never block the caller: a pipe nobody reads, a terminal stopped with
Ctrl-S or a stalled journald costs output, never a tick, a stop or the exit.

``unblocked()`` replaces ``sys.stdout`` and ``sys.stderr`` (only the interpreter's own: a
stream someone else put there, a test's capture, is left alone) with ``NonBlockingStream``s.
A write encodes the text and hands it to a queue (``queue.SimpleQueue``, whose ``put`` takes no
lock a caller could wait on and is safe even from a signal handler) and returns; a writer
thread writes the queue to a duplicate of the stream's descriptor, and only that thread can
block. More than ``QUEUE_BYTES`` waiting is dropped and counted. ``flush()`` returns at once;
``drain(timeout)`` waits a bounded time (the exit path: ``unblocked``'s end, a run's
``os._exit``). Writes of the C libraries straight to the descriptors are not covered.

Lines reach the descriptor whole: each thread's text is held until its newline (``print``
writes the text and the newline apart), and when stdout and stderr are one file (the journal,
``2>&1``) one writer thread writes both, in the order they were written, so a line of one
stream never lands inside a line of the other.

A closed standard descriptor (``jetbot-rt run 2>&-``) is opened on ``/dev/null`` first: no file
the command opens later can take its number (C code and faulthandler write to fd 1 and 2 by
number, which would land in a motor board's device or a recording). What would have gone to
a closed stdout is counted and said on stderr at the end, as a stdout nobody reads; with
stderr closed its lines (errors, stack dumps) are lost and only the exit code speaks.
"""

from __future__ import annotations

import atexit
import contextlib
import io
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
PENDING_CHARS = 1 << 16
"""A thread's text without a newline held at most this long, then written as it is."""
DRAIN_S = 0.5
"""How long the exit waits for the writers to hand their queues to the descriptors."""


class _Writer:
    """One thread that writes ``(stream, bytes)`` items, in queue order, to a duplicate of one
    descriptor; shared by the streams that write to the same file."""

    def __init__(self, fd: int, name: str) -> None:
        self.fd = os.dup(fd)  # its own: a dup2 onto fd 1/2 does not redirect it
        self.queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.users = 0
        self.thread = threading.Thread(target=self._write_all, daemon=True, name=name)
        self.thread.start()

    def _write_all(self) -> None:
        while True:
            item = self.queue.get()
            if item is None:  # a stream closed: the last one closes the descriptor
                self.users -= 1
                if self.users <= 0:
                    os.close(self.fd)
                    return
                continue
            if isinstance(item, threading.Event):
                item.set()
                continue
            stream, data = item
            stream._written += len(data)
            if stream.error is not None:
                stream.lost += len(data)
                continue
            try:
                self._write_one(data)
            except OSError as exc:  # the reader went away (EPIPE), a device error
                stream.error = exc.strerror or str(exc)
                stream.lost += len(data)

    def _write_one(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                written = os.write(self.fd, view)
            except BlockingIOError:  # someone made the descriptor non-blocking: wait for room
                select.select([], [self.fd], [], 0.05)
                continue
            view = view[written:]


class NonBlockingStream:
    """A text stream (``write``, ``flush``, ``fileno``, ``isatty``...) over a writer thread;
    ``writer``: another stream's, when both write to the same file."""

    def __init__(self, original: Any, limit: int = QUEUE_BYTES,
                 writer: _Writer | None = None) -> None:
        self.original = original
        self.encoding: str = original.encoding
        # A text that cannot be encoded is written escaped: a print must not raise on the exit path.
        errors = original.errors or "strict"
        self.errors: str = "backslashreplace" if errors == "strict" else errors
        self._limit = limit
        self._pending: dict[int, str] = {}  # thread ident: its text since its last newline
        self._queued = 0  # bytes, counted by the callers
        self._written = 0  # bytes taken off the queue, counted by the writer alone
        self.lost = 0
        """Bytes dropped: the queue was full, the reader had gone, or the exit could not wait."""
        self.error: str | None = None
        if writer is None:
            writer = _Writer(original.fileno(), f"jetbot-rt-{str(original.name).strip('<>')}")
        writer.users += 1
        self._writer = writer

    # ---- the text stream interface -----------------------------------------------------

    def write(self, text: str) -> int:
        ident = threading.get_ident()
        # pop, then put back: a signal handler's print in between (same thread) takes the
        # text held so far with its own line, nothing is lost or doubled
        held = self._pending.pop(ident, "") + text
        end = held.rfind("\n") + 1
        if end == 0 and len(held) <= PENDING_CHARS:
            self._pending[ident] = held
            return len(text)
        if end == 0:
            end = len(held)
        if end < len(held):
            self._pending[ident] = held[end:]
        self._put(held[:end])
        return len(text)

    def _put(self, text: str) -> None:
        data = text.encode(self.encoding, self.errors)
        if self.error is not None or self._queued - self._written + len(data) > self._limit:
            self.lost += len(data)
        elif data:
            self._queued += len(data)
            self._writer.queue.put((self, data))

    def writelines(self, lines: Any) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        """Hands the calling thread's unfinished line to the writer and returns at once."""
        held = self._pending.pop(threading.get_ident(), "")
        if held:
            self._put(held)

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
        """Wait at most ``timeout`` s for everything written so far to reach the descriptor;
        True if it did. What is still queued after that is counted as lost."""
        return self.drained(self.mark(), timeout)

    def mark(self) -> threading.Event:
        """An event the writer sets once everything written before it (every thread's
        unfinished line included) is written."""
        for ident in list(self._pending):
            held = self._pending.pop(ident, "")
            if held:
                self._put(held)
        done = threading.Event()
        self._writer.queue.put(done)
        return done

    def drained(self, mark: threading.Event, timeout: float) -> bool:
        if mark.wait(timeout):
            return self.error is None
        self.lost += max(0, self._queued - self._written)
        return False

    def close(self) -> None:
        """The writer closes its descriptor once it has written what is queued (if ever)."""
        self._writer.queue.put(None)


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


def fill_closed_descriptors() -> list[int]:
    """Opens ``/dev/null`` on each of fd 0, 1 and 2 that is closed; returns those numbers.
    Not close-on-exec: our children get them too."""
    closed = []
    for fd in (0, 1, 2):  # in order: open() takes the lowest free number
        try:
            os.fstat(fd)
        except OSError:
            closed.append(fd)
            null = os.open(os.devnull, os.O_RDWR)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
    return closed


def _same_file(a: Any, b: Any) -> bool:
    try:
        return os.path.samestat(os.fstat(a.fileno()), os.fstat(b.fileno()))
    except (OSError, ValueError, AttributeError):
        return False


@contextlib.contextmanager
def unblocked(enabled: bool = True, drain_s: float = DRAIN_S) -> Iterator[None]:
    """``sys.stdout`` and ``sys.stderr`` as ``NonBlockingStream``s inside; at the end the
    writers get at most ``drain_s`` together, what stdout lost is said on stderr, and the
    original streams are back."""
    closed = fill_closed_descriptors()
    installed: dict[str, NonBlockingStream] = {}
    previous: dict[str, Any] = {}
    if enabled:
        for fd, name in ((1, "stdout"), (2, "stderr")):
            original = _replaceable(name)
            if original is None and fd in closed and getattr(sys, name) is None:
                # the interpreter started without it: a stream on /dev/null that counts
                original = io.TextIOWrapper(io.FileIO(fd, "w", closefd=False),
                                            encoding="utf-8", errors="backslashreplace")
            if original is None:
                continue
            original.flush()  # nothing is written yet: this makes no system call
            shared = next((s._writer for s in installed.values()
                           if _same_file(s.original, original)), None)
            previous[name] = getattr(sys, name)
            installed[name] = NonBlockingStream(original, writer=shared)
            if fd in closed:
                installed[name].error = f"{name} was closed"
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
                setattr(sys, name, previous[name])
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
