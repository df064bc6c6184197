"""``jetbot-rt run --backend real`` end to end: real onnxruntime, a real GStreamer camera
(videotestsrc) and the emulated PCA9685 shared through its state file, read by the test."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import policy_models
import pytest

from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

MU = (1.0, -0.5)  # with max_speed 0.1: left forward 0.1, right reverse 0.05
STEP = 1 / 4096


class Robot:
    def __init__(self, root: Path, source: str = "gst:videotestsrc is-live=true pattern=snow"):
        self.root = root
        self.policy = policy_models.constant(root / "policy.onnx", MU)
        self.config = root / "robot.toml"
        self.config.write_text(f'[camera]\nsource = "{source}"\nstart_timeout = 5\n'
                               "[motors]\ni2c_retries = 1\n")
        self.telemetry = root / "telemetry.jsonl"
        self.env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(root / "run"))
        self.board = ["--board-emulator", str(root / "chip.json")]
        self.chip = PCA9685Emulator(0x60, state_file=root / "chip.json")
        self.process: subprocess.Popen[str] | None = None

    def start(self, duration: float = 30.0) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "jetbot_rt.cli", "run", "--backend", "real",
             "--policy", str(self.policy), "--config", str(self.config),
             "--telemetry", str(self.telemetry), "--duration", str(duration), *self.board],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=self.env,
        )

    def records(self) -> list[dict]:
        if not self.telemetry.exists():
            return []
        lines = self.telemetry.read_text().splitlines()
        return [json.loads(line) for line in lines if line.endswith("}")]

    def wait_for_ticks(self, count: int, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if sum("tick" in r for r in self.records()) >= count:
                return
            assert self.process is not None and self.process.poll() is None, self.finish()
            time.sleep(0.05)
        raise AssertionError(f"fewer than {count} ticks within {timeout} s")

    def finish(self, timeout: float = 30.0) -> tuple[int, str, str]:
        assert self.process is not None
        out, err = self.process.communicate(timeout=timeout)
        return self.process.returncode, out, err

    def safe_stops(self) -> list[dict]:
        return [r for r in self.records() if r.get("event") == "safe_stop"]

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()


@pytest.fixture
def robot(tmp_path):
    robot = Robot(tmp_path)
    yield robot
    robot.kill()


def assert_driving_forward_left_reverse_right(chip: PCA9685Emulator) -> None:
    chip.refresh()
    assert chip.channel(1).duty == pytest.approx(0.1, abs=STEP)  # left, forward channel
    assert chip.channel(0).duty == 0.0
    assert chip.channel(2).duty == 0.0
    assert chip.channel(3).duty == pytest.approx(0.05, abs=STEP)  # right, reverse channel


def test_sigterm_ends_with_every_output_off(robot) -> None:
    robot.start()
    robot.wait_for_ticks(30)  # about a second of driving at 30 Hz
    assert_driving_forward_left_reverse_right(robot.chip)
    robot.process.send_signal(signal.SIGTERM)
    code, _out, err = robot.finish()
    assert code == 0, err
    assert [s["reason"] for s in robot.safe_stops()] == ["SIGTERM received"]
    assert robot.chip.refresh().all_off()


def test_jetbot_rt_stop_latches_the_running_runtime(robot) -> None:
    robot.start()
    robot.wait_for_ticks(15)
    assert_driving_forward_left_reverse_right(robot.chip)
    stop = subprocess.run([sys.executable, "-m", "jetbot_rt.cli", "stop", *robot.board],
                          capture_output=True, text=True, timeout=30, env=robot.env)
    assert stop.returncode == 0, stop.stderr
    assert "latched its safe stop" in stop.stdout
    assert robot.chip.refresh().all_off()
    code, _out, err = robot.finish()
    assert code == 0, err
    (event,) = robot.safe_stops()
    assert event["reason"].startswith("jetbot-rt stop from pid ")
    assert robot.chip.refresh().all_off()


def test_a_camera_that_stops_delivering_latches_a_safe_stop(tmp_path) -> None:
    robot = Robot(tmp_path, "gst:videotestsrc is-live=true num-buffers=30")
    try:
        robot.start()
        code, _out, err = robot.finish()
    finally:
        robot.kill()
    assert code == 3, err
    (event,) = robot.safe_stops()
    assert event["reason"].startswith("stale frame")
    assert robot.chip.refresh().all_off()


def test_an_i2c_fault_while_driving_is_a_safe_stop_then_stop_clears_the_board(robot) -> None:
    robot.start()
    robot.wait_for_ticks(10)
    robot.chip.update(absent=True)  # the board stops answering (a loose cable)
    code, _out, err = robot.finish()
    assert code == 3, err
    (event,) = robot.safe_stops()
    assert "I2C bus 1 address 0x60" in event["reason"]
    assert not robot.chip.refresh().all_off()  # the chip kept its last duties
    robot.chip.update(absent=False)  # cable back; what systemd's ExecStopPost runs:
    stop = subprocess.run([sys.executable, "-m", "jetbot_rt.cli", "stop", *robot.board],
                          capture_output=True, text=True, timeout=30, env=robot.env)
    assert stop.returncode == 0, stop.stderr
    assert robot.chip.refresh().all_off()


def test_a_camera_that_cannot_start_is_a_usage_error_with_motors_untouched(tmp_path) -> None:
    robot = Robot(tmp_path, "gst:nosuchsrc")
    try:
        robot.start()
        code, _out, err = robot.finish()
    finally:
        robot.kill()
    assert code == 2
    assert 'no element "nosuchsrc"' in err
    assert len(err.strip().splitlines()) == 1
    assert not any("tick" in r for r in robot.records())
    assert robot.chip.refresh().all_off()
