"""``jetbot-rt check`` as a subprocess: emulated board, videotestsrc camera, a real ONNX model."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from check_helpers import check, rows, write_config

from jetbot_rt.commands.check import SPIN_DUTY
from jetbot_rt.hal.i2c import EMULATOR_FLAG
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator


def test_all_rows_pass_and_the_motors_never_move(robot) -> None:
    chip = PCA9685Emulator(0x60, state_file=robot / "chip.json")
    before = list(chip.registers)
    config = write_config(robot, "gst:videotestsrc is-live=true pattern=blue")
    result = check(robot, config)
    assert result.returncode == 0, result.stdout + result.stderr
    table = rows(result.stdout)
    assert "PCA9685 answers on I2C bus 1 at 0x60" in table["motor"]
    assert "layout waveshare" in table["motor"]
    assert "10 frames 96x96 RGB" in table["camera"]  # the policy's input size
    assert "mean colour R 0 G 0 B 255" in table["camera"]
    assert "input obs NHWC 96x96 float32 RGB 0-255; action output mu" in table["policy"]
    assert "max_speed 0.1 (the default; set [actions] max_speed)" in table["policy"]
    assert "CPUExecutionProvider" in table["providers"]
    assert all(" ok " in line for line in table.values())
    assert chip.refresh().registers == before  # only reads: not one register changed


def test_the_policy_row_states_the_max_speed_the_run_drives_at_and_why() -> None:
    from jetbot_rt.commands.check import run_max_speed

    assert run_max_speed(0.3, 0.5) == (0.3, "[actions] max_speed")
    assert run_max_speed(None, 0.5) == (0.5, "the model's metadata")
    assert run_max_speed(None, None) == (0.1, "the default; set [actions] max_speed")


def test_spin_pulses_and_ends_with_everything_off(robot) -> None:
    chip = PCA9685Emulator(0x60, state_file=robot / "chip.json")
    config = write_config(robot, "gst:videotestsrc is-live=true")
    result = check(robot, config, "--spin")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "spin" in rows(result.stdout)
    chip.refresh()
    # waveshare: left forward is the duty on channel 1, right forward on channel 2
    assert chip.peak_duty[1] == pytest.approx(SPIN_DUTY, abs=0.01)
    assert chip.peak_duty[2] == pytest.approx(SPIN_DUTY, abs=0.01)
    assert chip.peak_duty[0] == chip.peak_duty[3] == 0.0  # never reverse
    assert chip.all_off()


def test_failing_rows_make_a_non_zero_exit(robot) -> None:
    PCA9685Emulator(0x60, state_file=robot / "chip.json").update(absent=True)
    config = write_config(robot, "gst:nosuchsrc")
    result = check(robot, config)
    assert result.returncode == 1
    table = rows(result.stdout)
    assert "FAIL" in table["motor"] and "0x60" in table["motor"]
    assert "FAIL" in table["camera"] and 'no element "nosuchsrc"' in table["camera"]
    assert " ok " in table["policy"]


def test_a_camera_slower_than_configured_fails(robot) -> None:
    config = write_config(robot, "gst:videotestsrc is-live=true ! video/x-raw,framerate=10/1",
                          fps=30)
    result = check(robot, config)
    assert result.returncode == 1
    assert "slower than 30 fps" in rows(result.stdout)["camera"]


# [camera] fps 60 and --frames 15: check waits 2 s and two of [camera] fps's periods a frame
# (2.5 s), in which a 5 fps camera brings about 12, too few
@pytest.mark.parametrize(("source", "expected", "not_expected"), [
    # a live camera at 5 fps while [camera] fps says 60: slow, not stalled
    ("gst:videotestsrc is-live=true ! video/x-raw,framerate=5/1",
     "the camera delivers 5.0 fps, slower than [camera] fps 60", "stalled"),
    ("gst:videotestsrc is-live=true ! video/x-raw,framerate=4/1",
     "the camera delivers 4.0 fps, slower than [camera] fps 60", "stalled"),
    # (the rate is measured from arrival times: on a loaded host it may read 4.9 for 5, so the
    # number is compared within 0.5 fps, the words exactly)
    # a camera that stops after 3 frames: stalled
    ("gst:videotestsrc is-live=true num-buffers=3", "3 of 15 frames arrived, then the camera "
     "stalled", "slower"),
])
def test_a_slow_camera_is_called_slow_and_a_stalled_one_stalled(robot, source: str,
                                                                 expected: str,
                                                                 not_expected: str) -> None:
    config = write_config(robot, source, fps=60)
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(robot / "run"))
    result = subprocess.run(
        [sys.executable, "-m", "jetbot_rt.cli", "check", "--config", str(config),
         EMULATOR_FLAG, str(robot / "chip.json"),
         "--policy", str(robot / "policy.onnx"), "--frames", "15"],
        capture_output=True, text=True, timeout=60, env=env)
    assert result.returncode == 1, result.stdout + result.stderr
    camera = rows(result.stdout)["camera"]
    assert "FAIL" in camera and not_expected not in camera, camera
    parts = re.split(r"(\d+\.\d)", expected)  # words, a rate, words...
    found = re.search("".join(re.escape(part) if i % 2 == 0 else r"(\d+\.\d)"
                              for i, part in enumerate(parts)), camera)
    assert found, camera
    for got, want in zip(found.groups(), parts[1::2]):
        assert float(got) == pytest.approx(float(want), abs=0.5), camera


def test_a_signal_lost_during_the_imports_stops_the_spin_before_the_board_opens(
        monkeypatch) -> None:
    import signal

    from jetbot_rt.commands.check import spin_wheels
    from jetbot_rt.config.sections import Config
    from jetbot_rt.service import signals

    monkeypatch.setattr(signals, "_raised", [signal.SIGINT])  # raised, then swallowed
    with pytest.raises(signals.Interrupted):  # opening the default board would fail otherwise
        spin_wheels(Config())
