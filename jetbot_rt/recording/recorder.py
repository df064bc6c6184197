"""``--record DIR``: every tick's frame and record, written off the control thread.

Layout (docs/RECORDING.md, format version 2): ``meta.json`` (the run's config, policy, backend,
versions), ``ticks.jsonl`` (one record per tick as telemetry writes it, plus ``frame``, and the
events), ``frames.mkv`` (the frames as the policy received them, HuffYUV: lossless, so a replay
reproduces ``mu`` to round-off) and, once the run ends, ``summary.json``.

Encoding and writing happen in a writer process at the lowest CPU priority
(``jetbot_rt.recording.writer_process``, started by ``writer_command``): a thread would share
the control thread's interpreter lock, and a preempted low-priority thread holding it stalls
the tick (measured: ``bench_record.py``).
The control thread only copies the frame into a free slot of shared memory and writes one
line to a non-blocking pipe (``observe``). No free slot (``queue_frames`` frames wait for the
disk) or a full pipe: the frame or record is dropped and counted, never the tick. A write
error (disk full, directory removed) stops the recording with one line on stderr; the robot
keeps driving. ``close`` waits a bounded time; a writer that takes longer finishes alone.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import hashlib
import json
import mmap
import os
import platform
import select
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jetbot_rt.config import safe_file
from jetbot_rt.errors import UsageError
from jetbot_rt.recording.telemetry import dumps
from jetbot_rt.recording.writer_process import (
    DONE,
    ERROR,
    ERROR_TEXT,
    FRAMES_FILE,
    HEADER_BYTES,
    LOST,
    RECORDS,
    WRITTEN,
    layout,
)
from jetbot_rt.runtime.loop import TickResult

FORMAT = "jetbot_rt.recording.reader"
VERSION = 2
"""2: tick records may carry ``driver``, ``human`` and ``policy_mu`` (``jetbot-rt drive``)."""
F_SETPIPE_SZ = 1031  # fcntl: a pipe's capacity (Linux)
START_TIMEOUT = 20.0
"""Seconds the writer process may take to start (import OpenCV, open the video file)."""
CLOSE_TIMEOUT = 2.0
"""Seconds ``close`` waits for the writer; after that the run ends without it."""


WRITER_BOOTSTRAP = ("import sys; sys.path[:] = [p for p in sys.path if p]; "
                    "from jetbot_rt.recording.writer_process import main; sys.exit(main())")
"""The writer's ``-c`` program. ``python -m`` (or ``-c``) puts the working directory first on
``sys.path``: a ``jetbot_rt/`` (or ``json.py``...) planted in a shared directory would run as
the operator (root for the service) when someone records from there. Its first statement drops
that entry (``''``, which Python adds after ``site`` ran, so nothing was imported through it
yet), before any import. ``-P``/``PYTHONSAFEPATH`` would do the same but need Python 3.11; ``-I``
would also drop ``PYTHONPATH`` and the user's site-packages, where jetbot_rt may be installed.
The child also starts in ``/``, and is given absolute paths only."""


def writer_command(config_json: str) -> list[str]:
    """The writer process's command line (``jetbot_rt.recording.writer_process.main``)."""
    return [sys.executable, "-c", WRITER_BOOTSTRAP, config_json]


def sha256_of(path: str | Path) -> str:
    """The file's SHA-256, read through ``safe_file`` (a regular file; never blocks)."""
    digest = hashlib.sha256()
    with os.fdopen(safe_file.open_regular(path, "file"), "rb") as file:
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


def open_directory(path: Path) -> int:
    """The record directory, opened (``O_DIRECTORY|O_NOFOLLOW``): created here unless it
    exists. An existing one must be an empty directory of this user or root, not a symbolic
    link (someone else's link could name any directory: root would write there); a link among
    its parents must be this user's or root's too. Every file of the recording is created
    relative to the descriptor, so a rename of the directory's name afterwards redirects
    nothing. ``UsageError`` says what is refused."""
    try:
        safe_file.no_link_of_others_above(path, "record directory")
        path.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(FileExistsError):
            os.mkdir(path)  # never through a link at ``path``: that is EEXIST
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        if os.path.islink(path):
            raise UsageError(f"record directory {path} is a symbolic link (refused: name the "
                             "directory itself)") from None
        if exc.errno == errno.ENOTDIR:
            raise UsageError(f"record directory {path} exists and is not a directory") from None
        raise UsageError(f"cannot record to {path}: {exc.strerror or exc}") from None
    try:
        owner = os.fstat(fd).st_uid
        if owner not in (os.geteuid(), 0):
            raise UsageError(f"record directory {path} belongs to uid {owner}, not to this "
                             "user or root (refused: its owner could redirect the recording)")
        if os.listdir(fd):
            raise UsageError(f"record directory {path} exists and is not empty "
                             "(recordings are never overwritten)")
    except BaseException:
        os.close(fd)
        raise
    return fd


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
                 min_free_mb: float = 64.0, codec: str = "huffyuv",
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.path = Path(path)
        self.frame_size = frame_size
        self.fit = fit
        self.blocking = blocking
        self.clock = clock
        self.t0 = clock() if t0 is None else t0
        self.slots = queue_frames
        self.frames_sent = 0
        self.frames_dropped = 0
        self.records_lost = 0
        self.closed = False
        self._broken: str | None = None
        directory = open_directory(self.path)
        try:
            self._start_writer(directory, meta, rate_hz, min_free_mb, codec)
        finally:
            os.close(directory)  # the writer has its own
        self._pipe = self.process.stdin.fileno()
        with contextlib.suppress(OSError):  # room for ~1 s of records (Linux: 1 MiB max)
            fcntl.fcntl(self._pipe, F_SETPIPE_SZ, 1 << 20)
        os.set_blocking(self._pipe, blocking)

    def _start_writer(self, directory: int, meta: dict[str, Any], rate_hz: float,
                      min_free_mb: float, codec: str) -> None:
        """``meta.json``, then the writer process, given the directory's descriptor."""
        frame_size, queue_frames = self.frame_size, self.slots
        meta = {"format": FORMAT, "version": VERSION, "frame_size": list(frame_size),
                "rate_hz": rate_hz, "frames": FRAMES_FILE, "codec": codec,
                "versions": versions(),
                "started_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(),
                **meta}
        try:  # a new file: a link planted in a directory that existed is not followed
            with os.fdopen(safe_file.create_new("meta.json", dir_fd=directory), "w") as file:
                file.write(json.dumps(meta, indent=1) + "\n")
        except OSError as exc:
            raise UsageError(f"cannot record to {self.path}: {exc.strerror or exc}") from None
        width, height = frame_size
        memory = os.memfd_create("jetbot-rt-record")
        try:
            os.ftruncate(memory, HEADER_BYTES + queue_frames * width * height * 3)
            self._mm = mmap.mmap(memory, 0)
            self.process = subprocess.Popen(
                writer_command(json.dumps({
                    "path": os.path.abspath(self.path), "frame_size": [width, height],
                    "rate_hz": rate_hz, "slots": queue_frames, "min_free_mb": min_free_mb,
                    "codec": codec, "fd": memory, "directory": directory})),
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, pass_fds=(memory, directory),
                cwd="/",
            )
        finally:
            os.close(memory)
        self._header, self._frames = layout(self._mm, queue_frames, frame_size)
        assert self.process.stdin is not None and self.process.stdout is not None
        ready = f"error: the writer did not start within {START_TIMEOUT:g} s"
        if select.select([self.process.stdout], [], [], START_TIMEOUT)[0]:
            ready = self.process.stdout.readline().decode(errors="replace").strip()
        if ready != "ready":
            self.process.kill()
            self.process.wait()
            raise UsageError(f"cannot record to {self.path}: "
                             f"{ready.replace('error: ', '') or 'the writer did not start'}")

    @property
    def error(self) -> str | None:
        if self._broken is not None:
            return self._broken
        if self._header[ERROR]:
            return bytes(self._mm[ERROR_TEXT:HEADER_BYTES]).split(b"\0", 1)[0].decode(
                errors="replace")
        return None

    # ---- the control thread's side: never waits (unless ``blocking``) ---------------------

    def observe(self, result: TickResult) -> None:
        if self.closed or self.error is not None:
            self.records_lost += 1
            return
        if self.blocking:
            while self.frames_sent - self._header[DONE] >= self.slots and self.error is None:
                time.sleep(0.001)
        slot: int | None = None
        if self.frames_sent - int(self._header[DONE]) < self.slots:
            slot = self.frames_sent % self.slots
            image = result.image
            if self.fit is not None and image.shape[1::-1] != self.frame_size:
                image = self.fit(image)
            self._frames[slot] = image
        sent = self._send({"r": result.record(self.t0), "s": slot})
        if slot is not None and sent:
            self.frames_sent += 1
        else:
            self.frames_dropped += 1

    def event(self, name: str, **fields: Any) -> None:
        """An event record (``safe_stop``, ``end``...) in ``ticks.jsonl``, as telemetry has."""
        if not self.closed and self.error is None:
            self._send({"r": {"t": round(self.clock() - self.t0, 6), "event": name, **fields}})

    def _send(self, message: dict[str, Any]) -> bool:
        """One line to the writer; a full pipe (the writer is behind) loses it, counted."""
        data = (dumps(message) + "\n").encode()
        try:
            if len(data) > select.PIPE_BUF and not self.blocking:
                raise BlockingIOError  # only writes up to PIPE_BUF are all-or-nothing
            os.write(self._pipe, data)
            return True
        except BlockingIOError:
            self.records_lost += 1
        except OSError as exc:  # the writer is gone
            self._broken = f"the writer process ended ({exc.strerror or exc})"
            self.records_lost += 1
            print(f"jetbot-rt: recording {self.path} stopped ({self._broken}); still driving",
                  file=sys.stderr, flush=True)
        return False

    # ---- the end ----------------------------------------------------------------------------

    def counts(self) -> dict[str, Any]:
        counts: dict[str, Any] = {"path": str(self.path),
                                  "frames_written": int(self._header[WRITTEN]),
                                  "frames_dropped": self.frames_dropped,
                                  "records_written": int(self._header[RECORDS]),
                                  "records_lost": self.records_lost + int(self._header[LOST])}
        if self.error is not None:
            counts["error"] = self.error
        return counts

    def close(self, run_summary: dict[str, Any] | None = None,
              timeout: float | None = CLOSE_TIMEOUT) -> dict[str, Any]:
        """Let the writer finish for at most ``timeout`` s (None: until done); returns the
        counts for the summary. A writer that takes longer finishes on its own."""
        if self.closed:
            return self.counts()
        if run_summary is not None:
            self.event("end", **run_summary)
            self._send({"close": {**run_summary, "recorder": {
                "frames_dropped": self.frames_dropped, "records_lost": self.records_lost}}})
        self.closed = True
        with contextlib.suppress(OSError):
            os.close(self._pipe)  # the writer's end of input
        self.process.stdin = None  # closed above; Popen must not close it again
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            counts = self.counts()
            counts["unfinished"] = self.frames_sent - int(self._header[DONE])
            if "error" not in counts:  # a stopped recording has said so in its own line
                what = (f"the disk did not take the last {counts['unfinished']} frames"
                        if counts["unfinished"] else "the writer did not close its files")
                print(f"jetbot-rt: recording {self.path}: {what} within {timeout:g} s; "
                      "not waiting", file=sys.stderr, flush=True)
            return counts
        return self.counts()


def open_for_run(config: Any, backend: str, policy: Any, max_speed: float,
                 t0: float, extra: dict[str, Any] | None = None) -> Recorder | None:
    """The recorder ``jetbot-rt run`` asks for with ``--record`` or ``[record] path``;
    ``extra`` adds to (or replaces) the meta's keys (``jetbot-rt drive``: its source, input)."""
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
        **(extra or {}),
    }
    return Recorder(expand_path(config.record.path), meta, (spec.width, spec.height),
                    config.loop.rate_hz, queue_frames=config.record.queue_frames,
                    fit=policy.fit, t0=t0, min_free_mb=config.record.min_free_mb,
                    codec=config.record.codec)


def recording_line(counts: dict[str, Any]) -> str:
    """The run summary's line about the recording."""
    line = (f"{counts['path']}: {counts['frames_written']} frames, "
            f"{counts['frames_dropped']} dropped")
    if counts.get("error"):
        line += f"; stopped ({counts['error']}), {counts['records_lost']} ticks not recorded"
    elif counts.get("records_lost"):
        line += f", {counts['records_lost']} ticks not recorded"
    return line
