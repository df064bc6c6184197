"""Fault matrix: config values that cannot run together (class 7), threads that die
(class 7), telemetry that must be strict JSON (class 8), and the first frame's NaN.

Refusals go through the real CLI in a subprocess with the real backend on the emulated
PCA9685: exit 2, one line naming the keys, no traceback, and the board never written (the
emulator's state file is never created). Thread deaths need a backend that misbehaves
(tests/dying_backend.py), so they run ``main()`` in-process on the null drive.
"""

from __future__ import annotations

import json
import math
import os
import socket
import uuid
from pathlib import Path

import dying_backend
import policy_models
import pytest
from fault_helpers import needs_gst
from runner import processes_with, run_cli

from jetbot_rt.cli import main
from jetbot_rt.hal import registry
from jetbot_rt.recording.telemetry import Telemetry


def strict_loads(line: str) -> dict:
    def refuse(token: str) -> None:
        raise ValueError(f"not JSON: {token}")

    return json.loads(line, parse_constant=refuse)


def run_real(tmp_path: Path, config: str, *flags: str, env: dict | None = None):
    mark = f"fc{uuid.uuid4().hex[:12]}"
    policy = policy_models.constant(tmp_path / "policy.onnx", (1.0, 1.0))
    path = tmp_path / "config.toml"
    path.write_text(f'[camera]\nsource = "gst:videotestsrc name={mark} is-live=true"\n'
                    + config)
    chip = tmp_path / "chip.json"
    full_env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run"), **(env or {}))
    result = run_cli(["run", "--backend", "real", "--policy", str(policy), "--config",
                      str(path), "--board-emulator", str(chip), "--duration", "2", *flags],
                     env=full_env, timeout=60)
    assert not processes_with(mark)
    return result, chip


CROSS_KEY = [
    pytest.param("[loop]\nwatchdog_timeout = 0.05\n", (), ("[loop] watchdog_timeout",
                 "[loop] rate_hz 30"), id="watchdog-under-two-periods"),
    pytest.param("[loop]\nwatchdog_timeout = 0.015\n", ("--rate", "100"),
                 ("[loop] watchdog_timeout", "[loop] rate_hz 100"), id="watchdog-at-100-hz"),
    pytest.param("[loop]\nmax_frame_age = 0.1\n", ("--rate", "5"),
                 ("[loop] max_frame_age", "[loop] rate_hz 5"), id="frame-age-under-period"),
    # (the config goes on after [camera] source: a bare key lands in [camera])
    pytest.param("fps = 5\n[loop]\nmax_frame_age = 0.15\n", (),
                 ("[loop] max_frame_age", "[camera] fps 5"), id="frame-age-under-camera"),
]


@needs_gst
@pytest.mark.parametrize(("config", "flags", "names"), CROSS_KEY)
def test_values_that_cannot_run_together_are_refused(tmp_path: Path, config: str,
                                                     flags: tuple, names: tuple) -> None:
    result, chip = run_real(tmp_path, config, *flags)
    assert result.returncode == 2, result.stdout + result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert all(name in line for name in names), line
    assert not chip.exists(), "the board was opened"


@needs_gst
@pytest.mark.parametrize(("rate", "watchdog_usec"), [(1.0, 2_000_000), (2.0, 1_200_000)])
def test_ticks_further_apart_than_the_units_watchdog_allows_are_refused(
        tmp_path: Path, rate: float, watchdog_usec: int) -> None:
    """At 1 Hz under WatchdogSec=2s, a ping could come 2 s after the last: systemd would kill
    a healthy run. Refused before anything starts, naming the key and the unit's setting."""
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    name = f"\0jetbot-rt-test-{uuid.uuid4().hex}"
    notify.bind(name)
    try:
        result, chip = run_real(tmp_path, "", "--rate", str(rate),
                                env={"NOTIFY_SOCKET": "@" + name[1:],
                                     "WATCHDOG_USEC": str(watchdog_usec)})
    finally:
        notify.close()
    assert result.returncode == 2, result.stdout + result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert f"[loop] rate_hz {rate:g}" in line and "WatchdogSec" in line, line
    assert not chip.exists()


@pytest.mark.parametrize("rate", ["2", "5"])
def test_slow_rates_run_with_the_derived_frame_age(tmp_path: Path, rate: str) -> None:
    """At slow rates a fixed frame age would be shorter than the period (at or below 6.67 Hz,
    0.15 s): the derived default follows the period, so the run drives instead of stopping on
    its second tick."""
    policy = policy_models.constant(tmp_path / "p.onnx", (0.5, 0.5))
    telemetry = tmp_path / "t.jsonl"
    patient = tmp_path / "patient.toml"  # the watchdog is not the point (starved: it trips)
    patient.write_text("[loop]\nwatchdog_timeout = 1.0\n")
    result = run_cli(["run", "--backend", "sim", "--policy", str(policy), "--rate", rate,
                      "--duration", "1.5", "--config", str(patient)], telemetry=telemetry,
                     env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run")))
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.records[-1]["reason"].startswith("duration"), result.records[-1]
    (start,) = result.events("start")
    assert start["max_frame_age_s"] == pytest.approx(max(0.15, 1.5 / float(rate)))
    assert len(result.ticks) > 2  # the bug's runs ended on their second tick (3 in 1.5 s at 2 Hz)
    for line in telemetry.read_text().splitlines():
        strict_loads(line)


# ---- threads that die --------------------------------------------------------------------


@pytest.mark.parametrize(("behaviour", "reason"), [
    ("loop-thread-exits", "control loop ended without a stop"),
    ("helper-thread-dies", "thread camera-reader died: RuntimeError: reader lost its device"),
])
def test_a_thread_that_dies_is_a_safe_stop(tmp_path: Path, monkeypatch, capsys,
                                           behaviour: str, reason: str) -> None:
    """No thread may die silently: the loop thread ended by SystemExit (which no handler and
    no excepthook sees) or any other thread dying of an exception ends in the safe stop,
    exit 3, never "loop ended" with exit 0."""
    monkeypatch.setitem(registry.BACKEND_MODULES, "dying", "dying_backend")
    monkeypatch.setattr(dying_backend, "BEHAVIOUR", behaviour)
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path / "run"))
    policy = policy_models.constant(tmp_path / "p.onnx")
    telemetry = tmp_path / "t.jsonl"
    code = main(["run", "--backend", "dying", "--policy", str(policy), "--duration", "10",
                 "--telemetry", str(telemetry)])
    assert code == 3
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 1, err
    drive = dying_backend.DRIVES[-1]
    assert drive.last == (0.0, 0.0) and drive.writes > 5  # it drove, then stopped
    records = [strict_loads(line) for line in telemetry.read_text().splitlines()]
    assert records[-1]["event"] == "end" and records[-1]["reason"].startswith(reason)
    assert records[-1]["exit_code"] == 3


# ---- strict JSON ---------------------------------------------------------------------------


def test_a_zero_tick_run_writes_strict_json(tmp_path: Path, monkeypatch) -> None:
    """The first tick faults: the summary's tick statistics are NaN, written as null."""
    monkeypatch.setitem(registry.BACKEND_MODULES, "dying", "dying_backend")
    monkeypatch.setattr(dying_backend, "BEHAVIOUR", "first-tick-fails")
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path / "run"))
    policy = policy_models.constant(tmp_path / "p.onnx")
    telemetry = tmp_path / "t.jsonl"
    code = main(["run", "--backend", "dying", "--policy", str(policy),
                 "--telemetry", str(telemetry)])
    assert code == 3
    end = [strict_loads(line) for line in telemetry.read_text().splitlines()][-1]
    assert end["ticks"] == 0 and end["reason"] == "camera delivered no frame"
    assert end["tick_ms_p50"] is None and end["tick_ms_max"] is None


def test_non_finite_values_are_written_as_null_and_the_reason_keeps_them(tmp_path: Path) -> None:
    telemetry = Telemetry(tmp_path / "t.jsonl")
    telemetry.record({"tick": 1, "mu": [math.nan, math.inf], "cmd": [0.0, -math.inf],
                      "nested": {"x": [1.5, (math.nan,)]}})
    telemetry.event("safe_stop", reason="non-finite action mu=[nan, inf]", value=math.nan)
    telemetry.close()
    tick, stop = [strict_loads(line) for line in (tmp_path / "t.jsonl").read_text()
                  .splitlines()]
    assert tick["mu"] == [None, None] and tick["cmd"] == [0.0, None]
    assert tick["nested"] == {"x": [1.5, [None]]}
    assert stop["value"] is None and stop["reason"] == "non-finite action mu=[nan, inf]"


# ---- the first frame ---------------------------------------------------------------------


@needs_gst
@pytest.mark.parametrize("model", ["nan", "inf"])
def test_a_non_finite_answer_to_the_first_frame_is_bad_input(tmp_path: Path, model: str) -> None:
    """Decided (docs/SAFETY.md): a model whose answer to the first camera frame is not a
    finite action is bad input (exit 2), found in warm-up before any motor moved."""
    mark = f"fc{uuid.uuid4().hex[:12]}"
    make = policy_models.nan_when_dark if model == "nan" else policy_models.inf_when_dark
    policy = make(tmp_path / "policy.onnx", (1.0, 1.0))
    config = tmp_path / "config.toml"
    config.write_text(f'[camera]\nsource = "gst:videotestsrc name={mark} pattern=black '
                      'is-live=true"\n')
    chip = tmp_path / "chip.json"
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run"))
    telemetry = tmp_path / "t.jsonl"
    result = run_cli(["run", "--backend", "real", "--policy", str(policy), "--config",
                      str(config), "--board-emulator", str(chip)], telemetry=telemetry, env=env)
    assert result.returncode == 2, result.stdout + result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert "on the first camera frame" in line and "non-finite" in line, line
    assert not result.ticks
    from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

    assert PCA9685Emulator(0x60, state_file=chip).refresh().all_off()
    assert not processes_with(mark)


# ---- messages that must not mislead ---------------------------------------------------------


@pytest.mark.parametrize("name", [b"p\xe9.onnx", b"\xff\xfe-policy.onnx"])
def test_a_model_path_that_is_not_utf8_loads(tmp_path: Path, name: bytes) -> None:
    """onnxruntime takes only UTF-8 paths ("incompatible constructor arguments"): the runtime
    gives it the file's bytes instead, and shows the odd byte as \\xNN."""
    path = os.path.join(os.fsencode(tmp_path), name)
    policy_models.constant(Path(os.fsdecode(path)), (0.5, 0.5))
    telemetry = tmp_path / "t.jsonl"
    result = run_cli(["run", "--backend", "sim", "--policy", os.fsdecode(path),
                      "--duration", "0.5"], telemetry=telemetry,
                     env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run")))
    assert "incompatible constructor" not in result.stderr
    assert result.returncode in (0, 3), result.stderr  # 3: a watchdog trip on a loaded host
    assert result.ticks, result.stdout + result.stderr
    (start,) = result.events("start")
    assert start["policy"]["path"].endswith(name.decode("utf-8", "backslashreplace"))


@pytest.mark.parametrize("stated", ["NWHC", "nhwc", "HWC"])
def test_a_layout_in_the_metadata_that_is_not_one_is_named(tmp_path: Path, stated: str) -> None:
    policy = policy_models.constant(tmp_path / "p.onnx", metadata={"jetbot_rt.layout": stated})
    result = run_cli(["run", "--backend", "sim", "--policy", str(policy), "--duration", "1"],
                     env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run")))
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert f"jetbot_rt.layout = {stated!r} is not one of NHWC, NCHW" in line, line
    assert "cannot tell" not in line
