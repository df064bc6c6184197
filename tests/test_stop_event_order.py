"""The ``safe_stop`` event is logged only once the motors are zero.

The fault matrix reads the event as the moment of the zero write, and the record says
``cmd: [0, 0]``; an event logged before the zero write would make both untrue. The run is the
real ``jetbot-rt run --backend real`` (a GStreamer camera, the register-level PCA9685
emulator) in this process, so the telemetry can look at the emulated board at the very
moment each event is logged.
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import policy_models
import pytest

from jetbot_rt.commands import run as runtime_module
from jetbot_rt.recording.telemetry import Telemetry
from jetbot_rt.service.stop_socket import request_stop
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

pytestmark = pytest.mark.skipif(shutil.which("gst-launch-1.0") is None,
                                reason="needs gst-launch-1.0")


class BoardWatchingTelemetry(Telemetry):
    """The real telemetry; each event also records whether the board was all off when the
    event was logged."""

    def __init__(self, path: Path, chip_file: Path) -> None:
        super().__init__(path)
        self.chip = PCA9685Emulator(0x60, state_file=chip_file)

    def event(self, name: str, **fields: Any) -> Any:
        fields["board_all_off_when_logged"] = self.chip.refresh().all_off()
        return super().event(name, **fields)


@pytest.fixture
def signals_restored() -> Iterator[None]:
    """The runtime installs its signal handlers in this process: put pytest's back."""
    saved = {sig: signal.getsignal(sig) for sig in signal.valid_signals()
             if sig not in (signal.SIGKILL, signal.SIGSTOP)}
    yield
    for sig, handler in saved.items():
        if handler is not None:
            signal.signal(sig, handler)


def run_in_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, duration: float,
                   during: Any = None) -> tuple[int, list[dict]]:
    chip_file = tmp_path / "chip.json"
    policy = policy_models.constant(tmp_path / "policy.onnx", (1.0, -0.5))
    config = tmp_path / "robot.toml"
    config.write_text('[camera]\nsource = "gst:videotestsrc is-live=true"\nstart_timeout = 10\n'
                      "[loop]\nwarmup_runs = 1\n")
    parser = argparse.ArgumentParser()
    runtime_module.add_arguments(parser)
    args = parser.parse_args(["--backend", "real", "--policy", str(policy),
                              "--config", str(config), "--duration", str(duration),
                              "--board-emulator", str(chip_file)])
    runtime = runtime_module.Runtime(args)
    path = tmp_path / "t.jsonl"
    runtime.telemetry = BoardWatchingTelemetry(path, chip_file)
    helper = None
    if during is not None:
        helper = threading.Thread(target=during, args=(runtime,), daemon=True)
        helper.start()
    exit_code = runtime.run().exit_code
    if helper is not None:
        helper.join(30)
    assert PCA9685Emulator(0x60, state_file=chip_file).refresh().all_off()
    records = [json.loads(line) for line in path.read_text().splitlines()]
    return exit_code, records


def stop_request_after_ticks(runtime: Any) -> None:
    """``jetbot-rt stop`` from another shell, once the robot drives."""
    done = threading.Event()
    while not done.wait(0.02):
        if runtime.stats.ticks >= 5:
            break
        if runtime.latch.tripped:
            return
    request_stop()


class TestSafeStopEventAfterTheZeroWrite:
    @pytest.mark.usefixtures("signals_restored")
    def test_duration_end(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        exit_code, records = run_in_process(tmp_path, monkeypatch, duration=0.5)
        assert exit_code == 0
        self.check(records, "duration")

    @pytest.mark.usefixtures("signals_restored")
    def test_stop_request(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        exit_code, records = run_in_process(tmp_path, monkeypatch, duration=60,
                                            during=stop_request_after_ticks)
        assert exit_code == 0
        self.check(records, "jetbot-rt stop")

    @staticmethod
    def check(records: list[dict], reason: str) -> None:
        ticks = [r for r in records if "event" not in r]
        assert ticks and ticks[-1]["cmd"] == [0.1, -0.05], "it drove until the stop"
        [start] = [r for r in records if r.get("event") == "start"]
        assert start["board_all_off_when_logged"], "warm-up left the board off"
        [safe_stop] = [r for r in records if r.get("event") == "safe_stop"]
        assert safe_stop["reason"].startswith(reason), safe_stop
        assert safe_stop["cmd"] == [0.0, 0.0]
        assert safe_stop["board_all_off_when_logged"], "safe_stop logged before the zero write"
