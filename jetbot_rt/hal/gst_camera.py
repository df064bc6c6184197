"""A camera read from a ``gst-launch-1.0`` child process that writes raw RGB frames to a pipe.

pip's OpenCV has no GStreamer, so the pipeline runs as a child process instead of inside
``cv2.VideoCapture``: the source (CSI through Argus, a USB camera, or any GStreamer source)
is followed by conversion to RGB, scaling to the policy's input size and ``fdsink fd=1``. A reader
thread keeps only the newest frame and the ``time.monotonic()`` at which its last byte
arrived. If the pipeline dies or stalls, no new frame arrives, the frame ages and the control
loop refuses it (safe stop). The child never outlives the runtime: it gets SIGKILL when the
thread that started it dies (``PR_SET_PDEATHSIG``), and ``stop()`` kills it.
"""

from __future__ import annotations

import ctypes
import functools
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from fractions import Fraction
from typing import TYPE_CHECKING

import numpy as np

from jetbot_rt.errors import UsageError
from jetbot_rt.hal.base import Camera, Frame

if TYPE_CHECKING:
    from jetbot_rt.config.sections import CameraConfig

GST_LAUNCH = "gst-launch-1.0"


def gst_launch_path() -> str:
    """``gst-launch-1.0`` in PATH's absolute directories only: an empty or relative entry
    (``PATH=/usr/bin:``, a common slip) would run a program of that name planted in the
    working directory."""
    for directory in os.environ.get("PATH", os.defpath).split(os.pathsep):
        candidate = os.path.join(directory, GST_LAUNCH)
        if os.path.isabs(directory) and os.path.isfile(candidate) and os.access(candidate,
                                                                                os.X_OK):
            return candidate
    raise FileNotFoundError(GST_LAUNCH)
ARGUS_HINT = "for the CSI camera try: sudo systemctl restart nvargus-daemon"
NO_ARGUS = 'no element "nvarguscamerasrc"'
NO_ARGUS_HINT = (
    "this machine has no nvarguscamerasrc, so no CSI camera: it is not a Jetson, or JetPack's "
    'GStreamer plugins are missing; for a USB camera set [camera] source = "usb:/dev/video0"'
)
PR_SET_PDEATHSIG = 1
SCALE_METHOD = "hermite"
"""videoscale's multi-tap Hermite filter: it widens with the scale factor, so a 1280x720
frame scaled to 64x64 averages the pixels each output pixel covers, as the sim's render
stands for, instead of sampling a few of them (the default bilinear aliases checkerboards
into stripes). Measured against OpenCV's area average over videotestsrc patterns: mean
absolute difference 2.8 (bilinear 23.9), about 1 ms more CPU per frame
(benchmarks/bench_camera_scale.py, docs/SIM.md)."""


def _framerate(fps: float) -> str:
    rate = Fraction(fps).limit_denominator(1001)
    return f"{rate.numerator}/{rate.denominator}"


def source_pipeline(camera: CameraConfig) -> str:
    """The GStreamer source part of the pipeline for ``camera.source``."""
    if camera.source == "csi":
        return (
            f"nvarguscamerasrc sensor-id={camera.sensor_id} ! "
            f"video/x-raw(memory:NVMM),width={camera.capture_width},"
            f"height={camera.capture_height},framerate={_framerate(camera.fps)} ! "
            f"nvvidconv flip-method={camera.flip_method}"
        )
    if camera.source.startswith("usb:"):
        return f"v4l2src device={camera.source[4:]}"
    return camera.source[4:].strip()  # "gst:<pipeline>"


def full_pipeline(camera: CameraConfig, width: int, height: int) -> str:
    """Source, then RGB at the policy's size written to stdout."""
    return (
        f"{source_pipeline(camera)} ! videoconvert ! videoscale method={SCALE_METHOD} ! "
        f"video/x-raw,format=RGB,width={width},height={height} ! fdsink fd=1 sync=false"
    )


# Loaded here, in the parent: dlopen inside preexec_fn (after fork, in a process with other
# threads) could deadlock on a lock another thread held at the fork.
_LIBC = ctypes.CDLL(None, use_errno=True)
_PRCTL = _LIBC.prctl


def _die_with_parent(parent_pid: int) -> None:  # runs in the child between fork and exec
    _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)


def gst_error_line(stderr_lines: list[str]) -> str:
    """GStreamer's own error, as one line, from what ``gst-launch-1.0`` wrote to stderr."""
    lines = [line.strip() for line in stderr_lines if line.strip()]
    chosen = next((ln for ln in lines if ln.startswith(("ERROR", "WARNING: erroneous"))), None)
    if chosen is None:
        chosen = lines[-1] if lines else ""
    return re.sub(r"\s+", " ", chosen)


class GstCamera(Camera):
    """``start()`` waits up to ``camera.start_timeout`` for the first frame.

    Call ``start()`` from a thread that lives as long as the camera is used (the main
    thread): the kernel's parent-death signal follows the thread that forked the child.
    """

    def __init__(self, camera: CameraConfig, frame_size: tuple[int, int]) -> None:
        self.config = camera
        self.width, self.height = frame_size
        self.pipeline = full_pipeline(camera, self.width, self.height)
        self._process: subprocess.Popen[bytes] | None = None
        self._lock = threading.Lock()
        self._frame: Frame | None = None
        self._first_frame = threading.Event()
        self._cancelled = threading.Event()
        self._stderr: deque[str] = deque(maxlen=40)
        self._threads: list[threading.Thread] = []

    # ---- Camera ------------------------------------------------------------------------

    def start(self) -> None:
        try:
            self._process = subprocess.Popen(
                [gst_launch_path(), "-q", *shlex.split(self.pipeline)],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                bufsize=0,
                start_new_session=False,
                preexec_fn=functools.partial(_die_with_parent, os.getpid()),
            )
        except FileNotFoundError:
            raise UsageError(
                f"camera: {GST_LAUNCH} not found (install gstreamer1.0-tools)"
            ) from None
        self._threads = [
            threading.Thread(target=self._read_frames, name="gst-camera-frames", daemon=True),
            threading.Thread(target=self._read_stderr, name="gst-camera-stderr", daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        deadline = time.monotonic() + self.config.start_timeout
        while not self._first_frame.wait(0.02):
            if self._cancelled.is_set():
                self.stop()  # a stop request during start-up: no frame, no child left
                return
            if self._process.poll() is not None or time.monotonic() > deadline:
                self._fail_start()

    def cancel_start(self) -> None:
        self._cancelled.set()

    def read(self) -> Frame | None:
        with self._lock:
            return self._frame

    def stop(self) -> None:
        process, self._process = self._process, None
        if process is None:
            return
        if process.poll() is None:
            process.kill()
        try:
            process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:  # stuck in the kernel (a driver); do not hang the exit
            print(f"jetbot-rt: camera process {process.pid} did not exit after SIGKILL",
                  file=sys.stderr)
            return
        for thread in self._threads:
            thread.join(1.0)
        for stream in (process.stdout, process.stderr):
            if stream is not None:
                stream.close()

    # ---- internals ---------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def _fail_start(self) -> None:
        assert self._process is not None
        returncode = self._process.poll()
        exited = returncode is not None
        if exited:
            for thread in self._threads[1:]:
                thread.join(1.0)  # collect all of stderr
        message = gst_error_line(list(self._stderr))
        self.stop()
        if exited and not self._stderr:
            reason = (f"camera pipeline ended before its first frame "
                      f"({GST_LAUNCH} exit code {returncode})")
        elif exited:
            reason = f"camera pipeline failed to start: {message}"
        else:
            reason = f"camera gave no frame within {self.config.start_timeout:g} s"
            if self._stderr:
                reason += f": {message}"
        if self.config.source == "csi":
            reason += f" ({NO_ARGUS_HINT if NO_ARGUS in message else ARGUS_HINT})"
        raise UsageError(reason)

    def _read_frames(self) -> None:
        process = self._process
        assert process is not None and process.stdout is not None
        stream = process.stdout
        size = self.width * self.height * 3
        index = 0
        while True:
            buffer = bytearray(size)
            view = memoryview(buffer)
            got = 0
            while got < size:
                try:
                    count = stream.readinto(view[got:])  # type: ignore[attr-defined]
                except (OSError, ValueError):  # closed by stop()
                    return
                if not count:
                    return  # the pipeline ended: frames go stale, the loop stops
                got += count
            t_capture = time.monotonic()
            index += 1
            image = np.frombuffer(buffer, dtype=np.uint8).reshape(self.height, self.width, 3)
            with self._lock:
                self._frame = Frame(image, t_capture, index)
            self._first_frame.set()

    def _read_stderr(self) -> None:
        process = self._process
        assert process is not None and process.stderr is not None
        try:
            for raw in process.stderr:
                self._stderr.append(raw.decode(errors="replace"))
        except (OSError, ValueError):
            return
