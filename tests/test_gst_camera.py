"""The GStreamer camera with the real gst-launch-1.0 and videotestsrc."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from jetbot_rt.config.sections import CameraConfig
from jetbot_rt.errors import UsageError
from jetbot_rt.hal.gst_camera import GstCamera, full_pipeline, gst_error_line, source_pipeline


def camera(source: str, size: tuple[int, int] = (160, 120), **fields: object) -> GstCamera:
    return GstCamera(CameraConfig(source=source, start_timeout=5.0, **fields), size)


def wait_for_index(cam: GstCamera, index: int, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        frame = cam.read()
        if frame is not None and frame.index >= index:
            return
        time.sleep(0.01)
    raise AssertionError(f"frame {index} did not arrive")


def pid_alive(pid: int) -> bool:
    """True while ``pid`` runs; a zombie (dead, not yet reaped by init) counts as dead."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.parametrize(
    ("pattern", "rgb"), [("red", (255, 0, 0)), ("green", (0, 255, 0)), ("blue", (0, 0, 255))]
)
def test_solid_colour_arrives_as_rgb_at_the_requested_size(pattern, rgb) -> None:
    cam = camera(f"gst:videotestsrc is-live=true pattern={pattern}")
    cam.start()
    try:
        frame = cam.read()
        assert frame is not None
        assert frame.image.shape == (120, 160, 3)  # height x width x RGB
        assert frame.image.dtype == np.uint8
        assert tuple(frame.image.reshape(-1, 3).mean(axis=0).round()) == rgb
        assert 0 <= time.monotonic() - frame.t_capture < 5.0
    finally:
        cam.stop()


def test_a_large_frame_is_area_averaged_down_not_sampled() -> None:
    """8-pixel red/green checkers at 1280x720 scaled to 64x64: each output pixel covers
    20x11 input pixels, so an average is half red, half green everywhere, where a sampling
    filter (bilinear, GStreamer's default) keeps pure red and pure green squares."""
    cam = camera("gst:videotestsrc is-live=true pattern=checkers-8 ! "
                 "video/x-raw,width=1280,height=720", size=(64, 64))
    cam.start()
    try:
        image = cam.read().image.astype(int)
    finally:
        cam.stop()
    assert image.shape == (64, 64, 3)
    red_green = image[:, :, :2]
    assert red_green.min() > 70 and red_green.max() < 190


def test_reader_keeps_only_the_newest_frame() -> None:
    cam = camera("gst:videotestsrc is-live=true pattern=ball")
    cam.start()
    try:
        wait_for_index(cam, 4)
        first = cam.read()
        wait_for_index(cam, first.index + 2)
        newer = cam.read()
        assert newer.index > first.index and newer.t_capture > first.t_capture
    finally:
        cam.stop()


def test_a_pipeline_that_ends_leaves_the_last_frame_to_go_stale() -> None:
    cam = camera("gst:videotestsrc is-live=true num-buffers=5 pattern=white")
    cam.start()
    try:
        wait_for_index(cam, 5)
        time.sleep(0.4)
        last = cam.read()
        assert last.index == 5
        assert time.monotonic() - last.t_capture > 0.3  # older than any max_frame_age
        assert not cam.running
    finally:
        cam.stop()


def test_a_bad_element_gives_gstreamers_error_in_one_line() -> None:
    with pytest.raises(UsageError) as info:
        camera("gst:nosuchelement ! fakesink").start()
    message = str(info.value)
    assert 'no element "nosuchelement"' in message
    assert "\n" not in message


def test_csi_without_nvarguscamerasrc_says_so_rather_than_blaming_the_daemon() -> None:
    # No Argus on this machine: restarting nvargus-daemon cannot help, a USB camera can.
    with pytest.raises(UsageError, match="no nvarguscamerasrc, so no CSI camera") as error:
        camera("csi").start()
    assert "nvargus-daemon" not in str(error.value)


def test_no_first_frame_within_the_timeout_is_a_usage_error() -> None:
    # appsrc under gst-launch never gets data: the pipeline runs but no frame ever comes.
    cam = GstCamera(CameraConfig(source="gst:appsrc is-live=true caps=video/x-raw,format=RGB,"
                                 "width=64,height=48,framerate=30/1", start_timeout=0.5),
                    (64, 48))
    t0 = time.monotonic()
    with pytest.raises(UsageError, match=r"no frame within 0\.5 s"):
        cam.start()
    assert time.monotonic() - t0 < 5.0
    assert not cam.running


def test_stop_kills_the_child_and_is_idempotent() -> None:
    cam = camera("gst:videotestsrc is-live=true")
    cam.start()
    pid = cam._process.pid
    cam.stop()
    cam.stop()
    assert not pid_alive(pid)


CHILD = """
import sys
from jetbot_rt.config.sections import CameraConfig
from jetbot_rt.hal.gst_camera import GstCamera
cam = GstCamera(CameraConfig(source="gst:videotestsrc is-live=true"), (64, 48))
cam.start()
print(cam._process.pid, flush=True)
sys.stdin.read()
"""


def test_the_child_does_not_outlive_a_killed_runtime() -> None:
    runtime = subprocess.Popen(
        [sys.executable, "-c", CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )
    assert runtime.stdout is not None
    gst_pid = int(runtime.stdout.readline())
    assert pid_alive(gst_pid)
    runtime.send_signal(signal.SIGKILL)
    runtime.wait()
    deadline = time.monotonic() + 5.0
    while pid_alive(gst_pid) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not pid_alive(gst_pid)


def test_source_pipelines() -> None:
    csi = source_pipeline(CameraConfig(source="csi", sensor_id=1, capture_width=1640,
                                       capture_height=1232, fps=29.97, flip_method=2))
    assert csi == (
        "nvarguscamerasrc sensor-id=1 ! video/x-raw(memory:NVMM),width=1640,height=1232,"
        "framerate=2997/100 ! nvvidconv flip-method=2"
    )
    assert source_pipeline(CameraConfig(source="usb:/dev/video1")) == "v4l2src device=/dev/video1"
    full = full_pipeline(CameraConfig(source="gst:videotestsrc"), 224, 112)
    assert full.startswith("videotestsrc ! videoconvert ! videoscale method=hermite ! ")
    assert "video/x-raw,format=RGB,width=224,height=112 ! fdsink fd=1" in full


def test_gst_error_line_prefers_the_error_over_debug_lines() -> None:
    lines = ["Setting pipeline to PAUSED ...\n",
             "ERROR: from element /GstPipeline:pipeline0/GstV4l2Src:v4l2src0: Cannot open\n",
             "Additional debug info:\n"]
    assert gst_error_line(lines).startswith("ERROR: from element")


QUIET_CHILD = """
import sys
from jetbot_rt.config.sections import CameraConfig
from jetbot_rt.hal.gst_camera import GstCamera
# one frame a minute: after the first, the child writes nothing a broken pipe could end it on
source = "gst:videotestsrc is-live=true ! video/x-raw,framerate=1/60"
cam = GstCamera(CameraConfig(source=source, start_timeout=10.0), (64, 48))
cam.start()
print(cam._process.pid, flush=True)
sys.stdin.read()
"""


class TestAQuietChildDiesWithItsParent:
    """The child must not rely on a broken pipe to end: a camera that delivers rarely (or a
    stalled one) would keep gst-launch, and the camera device, after the runtime died."""

    @pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSEGV])
    def test_killed_runtime_takes_a_quiet_child_along(self, sig: int) -> None:
        runtime = subprocess.Popen(
            [sys.executable, "-c", QUIET_CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE
        )
        assert runtime.stdout is not None
        gst_pid = int(runtime.stdout.readline())
        try:
            assert pid_alive(gst_pid)
            runtime.send_signal(sig)
            runtime.wait()
            deadline = time.monotonic() + 10.0  # a liveness bound; the next frame is 60 s away
            while pid_alive(gst_pid) and time.monotonic() < deadline:
                time.sleep(0.02)
            assert not pid_alive(gst_pid), "gst-launch outlived the runtime"
        finally:
            if pid_alive(gst_pid):
                os.kill(gst_pid, signal.SIGKILL)
