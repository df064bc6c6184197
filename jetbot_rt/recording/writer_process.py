"""The recorder's writer process (``recorder.writer_command``: ``main`` with CONFIG_JSON).

A process of its own, at the lowest CPU priority, so that encoding never holds the control
loop's interpreter lock, nor its core. The runtime passes frames through a shared memory
(``slots`` frames, inherited as a file descriptor) and one JSON line per record on stdin:
``{"r": record, "s": slot or null}``. The writer encodes the slot's frame, writes the record
with its ``frame`` index, and counts in the shared header; the runtime reuses a slot once
``header[DONE]`` has passed it. It ends when stdin closes (the runtime ended or died).
"""

from __future__ import annotations

import contextlib
import errno
import json
import mmap
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jetbot_rt.config import safe_file
from jetbot_rt.recording.telemetry import dumps, finite

HEADER_BYTES = 4096
DONE, WRITTEN, RECORDS, LOST, ERROR = range(5)
"""int64 counters at the start of the header; the error text follows at ERROR_TEXT."""
ERROR_TEXT = 64
FRAMES_FILE = "frames.mkv"
CODECS = {"huffyuv": "HFYU", "ffv1": "FFV1"}
"""Lossless codecs (pip's opencv-python(-headless) writes both through its FFmpeg). At 224x224
on the 2-core VM: HuffYUV 0.3 ms of CPU and ~83 KB a frame, FFV1 2.8 ms and ~56 KB
(``benchmarks/bench_record_codecs.py``)."""


def layout(mm: mmap.mmap, slots: int, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The header counters and the frame slots over the shared memory."""
    width, height = size
    header = np.frombuffer(mm, np.int64, count=8)
    frames = np.frombuffer(mm, np.uint8, count=slots * height * width * 3,
                           offset=HEADER_BYTES).reshape(slots, height, width, 3)
    return header, frames


class Writer:
    def __init__(self, config: dict[str, Any], mm: mmap.mmap) -> None:
        self.path = Path(config["path"])  # for messages: files are made in ``directory``
        self.directory: int = config["directory"]
        self.min_free = float(config["min_free_mb"]) * 1e6
        self.mm = mm
        self.header, self.frames = layout(mm, config["slots"], tuple(config["frame_size"]))
        self.error: str | None = None
        self.run_summary: dict[str, Any] = {}
        self.next_space_check = 0.0
        # Every file is created new in the directory the runtime opened, never through a
        # link planted there; OpenCV writes the video through the open file.
        self.ticks = os.fdopen(safe_file.create_new("ticks.jsonl", dir_fd=self.directory), "w",
                               encoding="utf-8")
        self.fourcc = CODECS[config["codec"]]
        self.video_fd = safe_file.create_new(FRAMES_FILE, dir_fd=self.directory)
        with safe_file.path_for_library(self.video_fd, Path(FRAMES_FILE).suffix) as video_path:
            self.video = cv2.VideoWriter(video_path, cv2.VideoWriter_fourcc(*self.fourcc),
                                         config["rate_hz"], tuple(config["frame_size"]))

    def handle(self, message: dict[str, Any]) -> None:
        slot = message.get("s")
        try:
            if "close" in message:
                self.run_summary = message["close"]
            elif self.error is not None:
                self.header[LOST] += 1
            else:
                self.write(message["r"], slot)
        except (OSError, ValueError, cv2.error) as exc:
            self.fail(exc)
        finally:
            if slot is not None:
                self.header[DONE] += 1  # the slot is free again

    def write(self, record: dict[str, Any], slot: int | None) -> None:
        if os.fstat(self.ticks.fileno()).st_nlink == 0:
            raise FileNotFoundError("directory removed while recording")
        self.check_space()
        if "event" not in record:
            record["frame"] = None
            if slot is not None:
                self.video.write(np.ascontiguousarray(self.frames[slot][:, :, ::-1]))  # BGR
                record["frame"] = int(self.header[WRITTEN])
                self.header[WRITTEN] += 1
            self.header[RECORDS] += 1
        self.ticks.write(dumps(record) + "\n")
        self.ticks.flush()

    def check_space(self) -> None:
        """Once a second: the video writer cannot report a full disk, so look before it is."""
        now = time.monotonic()
        if now < self.next_space_check:
            return
        self.next_space_check = now + 1.0
        disk = os.fstatvfs(self.directory)
        free = disk.f_bavail * disk.f_frsize
        if free < self.min_free:
            raise OSError(errno.ENOSPC, f"disk nearly full: {free / 1e6:.0f} MB free, "
                          f"[record] min_free_mb is {self.min_free / 1e6:g}")

    def fail(self, exc: BaseException) -> None:
        self.error = str(getattr(exc, "strerror", None) or exc)
        self.header[LOST] += 1
        text = self.error.encode()[: HEADER_BYTES - ERROR_TEXT - 1]
        self.mm[ERROR_TEXT:ERROR_TEXT + len(text)] = text
        # The line before the flag: a recorder that sees the flag at close relies on it said.
        print(f"jetbot-rt: recording {self.path} stopped ({self.error}); still driving",
              file=sys.stderr, flush=True)
        self.header[ERROR] = 1

    def finish(self) -> None:
        with contextlib.suppress(Exception):
            self.video.release()
        with contextlib.suppress(OSError):
            os.close(self.video_fd)
        with contextlib.suppress(OSError, ValueError):
            self.ticks.close()
        runtime = self.run_summary.pop("recorder", {})
        counts = {"path": str(self.path), "frames_written": int(self.header[WRITTEN]),
                  "frames_dropped": runtime.get("frames_dropped", 0),
                  "records_written": int(self.header[RECORDS]),
                  "records_lost": runtime.get("records_lost", 0) + int(self.header[LOST]),
                  "error": self.error}
        with contextlib.suppress(OSError), os.fdopen(  # the directory may be gone: the
                safe_file.create_new("summary.json", dir_fd=self.directory), "w") as file:
            file.write(json.dumps(finite({**counts, "run": self.run_summary}), indent=1) + "\n")
        with contextlib.suppress(OSError):  # (the error said so)
            os.close(self.directory)


def main() -> int:
    # The runtime's terminal or service stop signals end the runtime; this process ends when
    # the runtime's pipe closes, after writing what it was given.
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT):
        signal.signal(signum, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.nice(19)
    config = json.loads(sys.argv[1])
    mm = mmap.mmap(config["fd"], 0)
    try:
        writer = Writer(config, mm)
    except OSError as exc:  # something already there (planted?), the disk, permissions
        name = f" {Path(exc.filename).name}" if exc.filename else ""
        print(f"error: cannot create{name}: {exc.strerror or exc}", flush=True)
        return 2
    if not writer.video.isOpened():
        print(f"error: this OpenCV ({cv2.__version__}) cannot write lossless {writer.fourcc} "
              "video; "
              "install opencv-python-headless to record", flush=True)
        return 2
    print("ready", flush=True)
    sys.stdout.close()
    for line in sys.stdin.buffer:
        try:
            message = json.loads(line)
        except ValueError:
            continue
        writer.handle(message)
    writer.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
