"""JSON Lines telemetry: one record per tick, plus event records carrying an ``event`` key.

Nothing here can block the control loop or the exit path. ``record``/``event`` append to a
bounded in-memory queue (a ``deque``: no lock the caller could wait on, not even a signal
handler's thread) and return; a writer thread serialises and writes. A full queue drops the
record and counts it. ``close`` waits a bounded time for the writer, then leaves: a reader of a
FIFO that stalls, or a disk that hangs, costs the records still queued (counted), never the
stop or the exit. The writer uses a raw file descriptor, so a writer thread still blocked in
``write`` at interpreter shutdown holds no Python lock.

A telemetry file that can no longer be written (disk full, directory removed, a FIFO's reader
gone) does not stop the robot: telemetry is for people, the safety chain does not depend on
it. The writer reports the failure once on stderr, stops writing and counts the lost records.
A removed file raises no write error on Linux (the records would go to an unlinked inode), so
the writer checks the link count before each record and treats that the same.

Records are strict JSON: a non-finite float (NaN, ±Infinity) is written as ``null``; the event
that reports a fault keeps the value in its ``reason`` text.

The previous run's telemetry is evidence (of a crash, say): opening never truncates. The file
is opened for appending, so a start refused before it drives adds its ``end`` record after the
previous run's; a run that starts (``rotate()``, at the ``start`` event) moves the previous
file to ``<path>.1`` (replacing the one before) and writes a new one.
"""

from __future__ import annotations

import collections
import errno
import json
import math
import os
import stat
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from jetbot_rt.errors import UsageError

if TYPE_CHECKING:
    from jetbot_rt.runtime.loop import TickResult

QUEUE_RECORDS = 4096
"""Records held in memory for the writer (over two minutes at 30 Hz)."""
CLOSE_TIMEOUT_S = 0.5
"""How long ``close`` waits for the writer to drain the queue before the process leaves."""


def finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None, in nested lists and dicts."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(item) for item in value]
    return value


def dumps(record: dict[str, Any]) -> str:
    """One strict-JSON line (no NaN/Infinity tokens)."""
    try:
        return json.dumps(record, separators=(",", ":"), allow_nan=False)
    except ValueError:  # a non-finite float somewhere: rare, so the walk only then
        return json.dumps(finite(record), separators=(",", ":"), allow_nan=False)


def _open(path: Path) -> int:
    """Open for writing without ever blocking: a FIFO without a reader is refused (ENXIO)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as exc:
        if exc.errno == errno.ENXIO:
            raise UsageError(
                f"cannot write telemetry {path}: a FIFO with no reader (start the reader first)"
            ) from None
        raise UsageError(f"cannot write telemetry {path}: {exc.strerror or exc}") from None
    # Writes block again (in the writer thread only): a FIFO's partial non-blocking writes
    # would cut records in half.
    os.set_blocking(fd, True)
    return fd


_ROTATE: dict[str, Any] = {}
"""Queue marker: the writer starts a new file here (``rotate``)."""


class Telemetry:
    def __init__(self, path: str | Path | None, queue_records: int = QUEUE_RECORDS) -> None:
        self.path = Path(path) if path else None
        self.t0 = time.monotonic()
        self.error: str | None = None
        self._dropped = 0  # by callers: queue full or writer failed
        self._failed = 0  # by the writer
        self._queue: collections.deque[dict[str, Any] | TickResult | None] = collections.deque()
        self._limit = queue_records
        self._wake = threading.Event()
        self._closing = False
        self._fd: int | None = None
        self._writer: threading.Thread | None = None
        if self.path is not None:
            self._fd = _open(self.path)
            self._regular = stat.S_ISREG(os.fstat(self._fd).st_mode)
            self._writer = threading.Thread(target=self._write_all, name="jetbot-rt-telemetry",
                                            daemon=True)
            self._writer.start()

    @property
    def enabled(self) -> bool:
        return self._writer is not None and not self._closing

    @property
    def lost(self) -> int:
        """Records dropped: queue full, write failed, or still queued when ``close`` gave up."""
        return self._dropped + self._failed

    def record(self, record: dict[str, Any] | TickResult) -> None:
        if not self.enabled:
            return
        if len(self._queue) >= self._limit or self.error is not None:
            self._dropped += 1
            return
        self._queue.append(record)
        self._wake.set()

    def observe(self, result: TickResult) -> None:
        """A tick observer: the tick's record, formatted by the writer thread."""
        self.record(result)

    def event(self, name: str, **fields: Any) -> dict[str, Any]:
        record = {"t": round(time.monotonic() - self.t0, 6), "event": name, **fields}
        self.record(record)
        return record

    def rotate(self) -> None:
        """The run starts: the writer moves a regular file that holds earlier records to
        ``<path>.1`` and goes on in a new file (a device or a pipe is kept as it is)."""
        if self.enabled:
            self._queue.append(_ROTATE)
            self._wake.set()

    def close(self, timeout: float = CLOSE_TIMEOUT_S) -> None:
        """Let the writer drain for at most ``timeout`` s; what is left is counted as lost."""
        writer = self._writer
        if writer is None or self._closing:
            return
        self._closing = True
        self._queue.append(None)  # the writer ends at this marker
        self._wake.set()
        writer.join(timeout)
        if writer.is_alive():
            # Blocked in write() (a stalled FIFO reader, a hung disk): leave it; the process
            # exit closes the descriptor.
            self._dropped += sum(1 for item in self._queue if item is not None) + 1
            print(f"jetbot-rt: telemetry {self.path}: the writer is blocked (a stalled reader?); "
                  "records still queued are lost", file=sys.stderr, flush=True)

    # ---- the writer thread -------------------------------------------------------------

    def _write_all(self) -> None:
        assert self._fd is not None
        while True:
            self._wake.wait()
            self._wake.clear()
            while self._queue:
                record = self._queue.popleft()
                if record is None:
                    os.close(self._fd)
                    return
                if record is _ROTATE:
                    self._rotate()
                    continue
                if self.error is not None:
                    self._failed += 1
                    continue
                try:
                    self._write_one(record)
                except (OSError, ValueError, TypeError) as exc:
                    self._failed += 1
                    self._report(str(getattr(exc, "strerror", None) or exc))

    def _write_one(self, record: dict[str, Any] | TickResult) -> None:
        assert self._fd is not None
        if not isinstance(record, dict):
            record = record.record(self.t0)
        if self._regular and os.fstat(self._fd).st_nlink == 0:
            raise FileNotFoundError("file removed while running")
        data = (dumps(record) + "\n").encode("utf-8", "backslashreplace")
        view = memoryview(data)
        while view:
            written = os.write(self._fd, view)
            view = view[written:]

    def _rotate(self) -> None:
        assert self._fd is not None and self.path is not None
        if not self._regular or self.error is not None or os.fstat(self._fd).st_size == 0:
            return
        try:
            os.replace(self.path, self.path.with_name(self.path.name + ".1"))
            fd = _open(self.path)
        except (OSError, UsageError) as exc:
            self._report(f"cannot move the previous file aside: {exc}")
            return
        os.close(self._fd)
        self._fd = fd

    def _report(self, error: str) -> None:
        if self.error is None:
            self.error = error
            print(f"jetbot-rt: telemetry {self.path} not writable any more "
                  f"({error}); still driving, records dropped", file=sys.stderr, flush=True)
