"""``--record DIR``: every tick's frame and record, written off the control thread.

Layout (docs/RECORDING.md, format version 1): ``meta.json`` (the run's config, policy, backend,
versions), ``ticks.jsonl`` (one record per tick as telemetry writes it, plus ``frame``, and the
events), ``frames.mkv`` (the frames as the policy received them, FFV1: lossless, so a replay
reproduces ``mu`` to round-off) and, once the run ends, ``summary.json``.

The control thread only hands the tick over (``observe``): an append to a bounded queue that
takes no lock. When more than ``queue_frames`` frames wait for the disk, the tick's frame is dropped
and counted, never the tick. A write error (disk full, directory removed) stops the recording
with one line on stderr; the robot keeps driving. ``close`` waits a bounded time.
"""

from __future__ import annotations

import collections
import contextlib
import datetime
import errno
import hashlib
import json
import os
import platform
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from jetbot_rt.errors import UsageError
from jetbot_rt.loop import TickResult
from jetbot_rt.telemetry import dumps, finite

FORMAT = "jetbot_rt.recording"
VERSION = 1
FRAMES_FILE = "frames.mkv"
FOURCC = "FFV1"  # lossless; pip's opencv-python(-headless) writes it through its FFmpeg
CLOSE_TIMEOUT = 2.0
"""Seconds ``close`` waits for the writer; after that the run ends without it."""
IDLE_SLEEP = 0.01
"""Seconds the writer sleeps when it has nothing to write (it takes no lock to be woken)."""


def sha256_of(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def versions() -> dict[str, str]:
    import jetbot_rt

    found = {"jetbot_rt": jetbot_rt.__version__, "python": platform.python_version(),
             "numpy": np.__version__, "opencv": cv2.__version__}
    with contextlib.suppress(ImportError):
        import onnxruntime

        found["onnxruntime"] = onnxruntime.__version__
    return found


def expand_path(template: str) -> Path:
    """``{time}`` in a configured path becomes the UTC start time, so each run gets its own."""
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    return Path(template.replace("{time}", stamp))


def prepare_directory(path: Path) -> None:
    """Create ``path``; an existing non-empty directory (an earlier recording) is refused."""
    try:
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            raise UsageError(f"record directory {path} exists and is not empty "
                             "(recordings are never overwritten)")
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"cannot record to {path}: {exc.strerror or exc}") from None


def _dump(record: dict[str, Any]) -> str:
    return dumps(record) + "\n"  # strict JSON, as telemetry writes it


class Recorder:
    """Writes one recording. ``observe`` is a tick observer (``ControlLoop.observers``).

    ``fit`` brings a frame to ``frame_size`` the way the policy does (for a camera that
    delivers another size). ``blocking`` makes ``observe`` wait for room instead of dropping
    (offline use: evaluation, where nothing waits on the caller). ``t`` in the records counts
    from ``t0`` on ``clock`` (monotonic time; simulated time for an evaluation).
    """

    def __init__(self, path: str | Path, meta: dict[str, Any], frame_size: tuple[int, int],
                 rate_hz: float, *, queue_frames: int = 64,
                 fit: Callable[[np.ndarray], np.ndarray] | None = None,
                 blocking: bool = False, t0: float | None = None,
                 min_free_mb: float = 64.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.path = Path(path)
        prepare_directory(self.path)
        self.frame_size = frame_size
        self.fit = fit
        self.blocking = blocking
        self.min_free = min_free_mb * 1e6
        self._next_space_check = 0.0
        self.clock = clock
        self.t0 = clock() if t0 is None else t0
        self.frames_written = 0
        self.frames_dropped = 0
        self.records_written = 0
        self.records_lost = 0
        self.error: str | None = None
        # The hand-over takes no lock the writer could hold: a deque's append and popleft are
        # atomic, and each counter has one writer (frames in: the control thread; out: the
        # writer thread). A lock held by a preempted writer would stall the tick.
        self._items: collections.deque[Any] = collections.deque()
        self._max_items = max(1024, 8 * queue_frames)
        self._max_frames = queue_frames
        self._frames_in = 0
        self._frames_out = 0
        self._closing = threading.Event()
        self._run_summary: dict[str, Any] = {}
        meta = {"format": FORMAT, "version": VERSION, "frame_size": list(frame_size),
                "rate_hz": rate_hz, "frames": FRAMES_FILE, "versions": versions(),
                "started_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(),
                **meta}
        try:
            (self.path / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
            self._ticks: IO[str] = open(self.path / "ticks.jsonl", "w", encoding="utf-8",  # noqa: SIM115
                                        buffering=1)
        except OSError as exc:
            raise UsageError(f"cannot record to {self.path}: {exc.strerror or exc}") from None
        self._video = cv2.VideoWriter(str(self.path / FRAMES_FILE),
                                      cv2.VideoWriter_fourcc(*FOURCC), rate_hz, frame_size)
        if not self._video.isOpened():
            self._ticks.close()
            raise UsageError(f"this OpenCV ({cv2.__version__}) cannot write lossless {FOURCC} "
                             "video; install opencv-python-headless to record")
        self._thread = threading.Thread(target=self._write_all, name="jetbot-rt-recorder",
                                        daemon=True)
        self._thread.start()

    # ---- the control thread's side: never waits (unless ``blocking``) ---------------------

    def observe(self, result: TickResult) -> None:
        if self.error is not None or self._closing.is_set():
            self.records_lost += 1
            return
        image: np.ndarray | None = result.image
        if self.blocking:
            self._wait(lambda: self._frames_in - self._frames_out < self._max_frames)
        if self._frames_in - self._frames_out >= self._max_frames:
            image = None
            self.frames_dropped += 1
        self._put((result, image))

    def event(self, name: str, **fields: Any) -> None:
        """An event record (``safe_stop``, ``end``...) in ``ticks.jsonl``, as telemetry has."""
        if self.error is None and not self._closing.is_set():
            self._put({"t": round(self.clock() - self.t0, 6), "event": name, **fields})

    def _put(self, item: Any) -> None:
        if self.blocking:
            self._wait(lambda: len(self._items) < self._max_items)
        has_frame = isinstance(item, tuple) and item[1] is not None
        if len(self._items) >= self._max_items:
            self.records_lost += 1
            self.frames_dropped += has_frame
            return
        self._frames_in += has_frame
        self._items.append(item)

    def _wait(self, ready: Callable[[], bool]) -> None:
        """``blocking`` mode only: until ``ready()`` or the writer is gone."""
        while not ready() and self.error is None and self._thread.is_alive():
            time.sleep(0.001)

    # ---- the writer thread ------------------------------------------------------------------

    def _write_all(self) -> None:
        # The lowest CPU priority, for this thread only (on Linux a thread has its own nice
        # value): encoding yields the core to the control thread. This is safe only because
        # the hand-over takes no lock (see __init__): measured with queue.Queue and a
        # semaphore, a preempted writer holding their lock stalled ticks (p99 jitter x3.4).
        with contextlib.suppress(AttributeError, OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        while True:
            try:
                item = self._items.popleft()
            except IndexError:
                if self._closing.is_set():
                    break
                time.sleep(IDLE_SLEEP)
                continue
            image = item[1] if isinstance(item, tuple) else None
            try:
                if self.error is None:
                    self._write(item)
                else:
                    self.records_lost += 1
            except (OSError, ValueError, cv2.error) as exc:
                self._fail(exc)
            finally:
                if image is not None:
                    self._frames_out += 1
        self._finish()

    def _write(self, item: Any) -> None:
        if os.fstat(self._ticks.fileno()).st_nlink == 0:
            raise FileNotFoundError("directory removed while recording")
        self._check_space()
        if isinstance(item, dict):
            self._ticks.write(_dump(item))
            return
        result, image = item
        record = result.record(self.t0)
        record["frame"] = None
        if image is not None:
            if self.fit is not None and image.shape[1::-1] != self.frame_size:
                image = self.fit(image)
            self._video.write(np.ascontiguousarray(image[:, :, ::-1]))  # RGB -> the file's BGR
            record["frame"] = self.frames_written
            self.frames_written += 1
        self._ticks.write(_dump(record))
        self.records_written += 1

    def _check_space(self) -> None:
        """Once a second: the video writer cannot report a full disk, so look before it is."""
        now = time.monotonic()
        if now < self._next_space_check:
            return
        self._next_space_check = now + 1.0
        disk = os.statvfs(self.path)
        free = disk.f_bavail * disk.f_frsize
        if free < self.min_free:
            raise OSError(errno.ENOSPC, f"disk nearly full: {free / 1e6:.0f} MB free, "
                          f"[record] min_free_mb is {self.min_free / 1e6:g}")

    def _fail(self, exc: BaseException) -> None:
        self.error = str(getattr(exc, "strerror", None) or exc)
        self.records_lost += 1
        print(f"jetbot-rt: recording {self.path} stopped ({self.error}); still driving",
              file=sys.stderr, flush=True)

    def _finish(self) -> None:
        with contextlib.suppress(Exception):
            self._video.release()
        with contextlib.suppress(OSError, ValueError):
            self._ticks.close()
        with contextlib.suppress(OSError):  # the directory may be gone: the error said so
            (self.path / "summary.json").write_text(
                json.dumps(finite({**self.counts(), "run": self._run_summary}), indent=1) + "\n")

    # ---- the end ----------------------------------------------------------------------------

    def counts(self) -> dict[str, Any]:
        counts: dict[str, Any] = {"path": str(self.path), "frames_written": self.frames_written,
                                  "frames_dropped": self.frames_dropped,
                                  "records_written": self.records_written,
                                  "records_lost": self.records_lost}
        if self.error is not None:
            counts["error"] = self.error
        return counts

    def close(self, run_summary: dict[str, Any] | None = None,
              timeout: float | None = CLOSE_TIMEOUT) -> dict[str, Any]:
        """Let the writer drain for at most ``timeout`` s (None: until done); returns the
        counts for the summary."""
        if self._closing.is_set():
            return self.counts()
        if run_summary is not None:
            self.event("end", **run_summary)
            self._run_summary = run_summary
        self._closing.set()
        self._thread.join(timeout)
        counts = self.counts()
        if self._thread.is_alive():
            counts["unfinished"] = len(self._items)
            print(f"jetbot-rt: recording {self.path}: the disk did not take the last "
                  f"{counts['unfinished']} records within {timeout:g} s; not waiting",
                  file=sys.stderr, flush=True)
        return counts


def open_for_run(config: Any, backend: str, policy: Any, max_speed: float,
                 t0: float) -> Recorder | None:
    """The recorder ``jetbot-rt run`` asks for with ``--record`` or ``[record] path``."""
    if not config.record.path:
        return None
    import dataclasses

    spec = policy.spec
    meta = {
        "source": "jetbot-rt run",
        "backend": backend,
        "policy": {**policy.describe(), "sha256": sha256_of(policy.path),
                   "metadata": policy.metadata},
        "max_speed": max_speed,
        "config": dataclasses.asdict(config),
        "argv": sys.argv,
    }
    return Recorder(expand_path(config.record.path), meta, (spec.width, spec.height),
                    config.loop.rate_hz, queue_frames=config.record.queue_frames,
                    fit=policy.fit, t0=t0, min_free_mb=config.record.min_free_mb)


def recording_line(counts: dict[str, Any]) -> str:
    """The run summary's line about the recording."""
    line = (f"{counts['path']}: {counts['frames_written']} frames, "
            f"{counts['frames_dropped']} dropped")
    if counts.get("error"):
        line += f"; stopped ({counts['error']}), {counts['records_lost']} ticks not recorded"
    elif counts.get("records_lost"):
        line += f", {counts['records_lost']} ticks not recorded"
    return line
