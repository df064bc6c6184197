"""Errors nobody planned for still end in a safe stop with one line and exit code 3."""

import json

import broken_backend
import policy_models
from runner import run_cli

from jetbot_rt.cli import main
from jetbot_rt.hal import registry


def test_unexpected_exception_is_a_safe_stop(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(registry.BACKEND_MODULES, "broken", "broken_backend")
    policy = policy_models.constant(tmp_path / "p.onnx")
    telemetry = tmp_path / "t.jsonl"
    code = main(["run", "--backend", "broken", "--policy", str(policy),
                 "--telemetry", str(telemetry)])
    assert code == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["jetbot-rt run: unexpected error: RuntimeError: driver bug"]
    assert broken_backend.DRIVES[-1].last == (0.0, 0.0)
    end = json.loads(telemetry.read_text().splitlines()[-1])
    assert end["event"] == "end" and end["exit_code"] == 3 and end["cmd"] == [0.0, 0.0]


def test_control_socket_that_cannot_be_created_is_a_usage_error(tmp_path, monkeypatch):
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path / ("x" * 120)))
    policy = policy_models.constant(tmp_path / "p.onnx")
    result = run_cli(["run", "--backend", "sim", "--policy", str(policy), "--duration", "1"])
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot create the control socket" in lines[0]


def test_every_way_out_releases_the_robot_between_two_zero_writes_the_last_write_zero(
        tmp_path, monkeypatch):
    """The phases' exits run in reverse: the drive phase's watchdog, the connect phase's zero
    and the robot's release; then the stop phase's own zero is the last write."""
    import logging_backend

    monkeypatch.setitem(registry.BACKEND_MODULES, "logging", "logging_backend")
    policy = policy_models.constant(tmp_path / "p.onnx", (1.0, -0.5))
    code = main(["run", "--backend", "logging", "--policy", str(policy), "--duration", "0.3"])
    assert code == 0
    log = logging_backend.LOG
    assert "write" in log, "it drove"
    after_driving = log[len(log) - log[::-1].index("write"):]
    # the latch's own zero write, then the exits: zero, the robot released, zero last
    assert after_driving[-3:] == ["camera stop", "disconnect", "zero"]
    assert after_driving[:-3] and set(after_driving[:-3]) == {"zero"}
