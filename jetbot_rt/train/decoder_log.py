"""FFmpeg's own log lines kept off the user's stderr while the trainer reads recordings."""

from __future__ import annotations

import os

AV_LOG_QUIET = -8


def quiet_ffmpeg() -> None:
    """Silence FFmpeg inside OpenCV for this process; call it before the first
    ``cv2.VideoCapture``. A truncated frames.mkv makes FFmpeg log "File ended prematurely"
    at its error level, beside our own one-line error; the reader ends at the last whole
    frame either way, and finetune says in one line what it lacks.

    Why this knob: OpenCV's FFmpeg backend sets av_log's level once per process, when its
    first capture opens, from ``OPENCV_FFMPEG_LOGLEVEL`` (default: errors), so the variable
    works when set after ``import cv2`` but not after a capture opened. ``OPENCV_LOG_LEVEL``
    and ``cv2.utils.logging.setLogLevel`` govern OpenCV's own log, not av_log (tried with
    the installed opencv 5.0: the line still came; it has no ``cv2.setLogLevel``), and the
    wheel bundles its own libavutil, so calling ``av_log_set_level`` by ctypes would have
    to find that copy. A person who set ``OPENCV_FFMPEG_DEBUG`` or a level keeps theirs."""
    if "OPENCV_FFMPEG_DEBUG" not in os.environ:
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", str(AV_LOG_QUIET))
