"""What the fault tests share: the cameras they drive with (GStreamer test sources), the real
backend's config, the policy's constant output, where measured figures go, and the check that
no gst-launch child outlived its runtime."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from runner import processes_with, wait_for

MU = (1.0, -0.5)  # max_speed 0.1: left +0.1, right -0.05

needs_gst = pytest.mark.skipif(shutil.which("gst-launch-1.0") is None,
                               reason="needs gst-launch-1.0")


def live_camera(mark: str) -> str:
    return f"videotestsrc name={mark} is-live=true"


class SwitchableCamera:
    """A camera whose picture the test changes while the runtime drives: gst-launch re-reads
    one raw GRAY8 frame file for every frame, 30 per second of wall time, and the test replaces
    that file whole. A fault that comes with a black frame then starts after a count of the
    loop's own ticks; a timeline of frames counted from gst-launch's start left a loaded host's
    slow start-up too little driving before it (seen: 6 ticks for the 10 asserted)."""

    WIDTH, HEIGHT = 320, 240

    def __init__(self, directory: Path, mark: str) -> None:
        self.path = directory / f"{mark}.gray"
        self.pipeline = (f"multifilesrc name={mark} location={self.path} loop=true ! "
                         f"rawvideoparse format=gray8 width={self.WIDTH} height={self.HEIGHT} "
                         "framerate=30/1 ! identity sync=true")
        self.show_pattern()

    def show_pattern(self) -> None:
        """A horizontal ramp from black to white: a mean far from the policies' dark test."""
        ramp = bytes(x * 256 // self.WIDTH for x in range(self.WIDTH))
        self._show(ramp * self.HEIGHT)

    def show_black(self) -> None:
        self._show(bytes(self.WIDTH * self.HEIGHT))

    def _show(self, frame: bytes) -> None:
        new = self.path.with_suffix(".new")
        new.write_bytes(frame)
        os.replace(new, self.path)


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
