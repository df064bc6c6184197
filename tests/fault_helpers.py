"""What the fault tests share: the cameras they drive with (GStreamer test sources), the real
backend's config, the policy's constant output, where measured figures go, and the check that
no gst-launch child outlived its runtime."""

from __future__ import annotations

import json
import os
import shutil

import pytest
from runner import processes_with, wait_for

MU = (1.0, -0.5)  # max_speed 0.1: left +0.1, right -0.05
FPS_CAPS = "video/x-raw,width=320,height=240,framerate=30/1"

needs_gst = pytest.mark.skipif(shutil.which("gst-launch-1.0") is None,
                               reason="needs gst-launch-1.0")


def live_camera(mark: str) -> str:
    return f"videotestsrc name={mark} is-live=true"


def timeline_camera(mark: str, normal: int, dark: int | None, then_normal: bool = False) -> str:
    """``normal`` frames of a test pattern, then ``dark`` black frames (None: forever), then
    (``then_normal``) the pattern again, all at 30 frames per second of wall time."""
    dark_frames = "" if dark is None else f" num-buffers={dark}"
    parts = [f"videotestsrc name={mark} num-buffers={normal} ! {FPS_CAPS} ! c.",
             f"videotestsrc pattern=black{dark_frames} ! {FPS_CAPS} ! c."]
    if then_normal:
        parts.append(f"videotestsrc ! {FPS_CAPS} ! c.")
    return " ".join(parts) + " concat name=c ! identity sync=true"


def real_config(source: str, motors: str = "i2c_retries = 3") -> str:
    return (f'[camera]\nsource = "gst:{source}"\nstart_timeout = 10\n'
            f"[motors]\n{motors}\n")


def record_figures(name: str, **figures: object) -> None:
    path = os.environ.get("JETBOT_RT_FAULT_FIGURES")
    if path:
        with open(path, "a") as out:
            out.write(json.dumps({"case": name, **figures}) + "\n")


def assert_no_gst_left(mark: str) -> None:
    gone = wait_for(lambda: not processes_with(mark), 3.0, interval=0.05)
    assert gone is not None, f"gst-launch left behind: {processes_with(mark)}"
