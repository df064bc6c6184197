"""Fault matrix, files the runtime could destroy or misread (class 6): a telemetry
path that is the policy or the config is refused (exit 2) before anything is opened; a start,
even one refused with exit 2, never truncates the previous run's telemetry (a refused start
appends its ``end`` record; a run that starts moves the previous file to ``<path>.1``); an
empty policy or telemetry path is an error, not "the bundled policy" or "no telemetry".

Refusals run the real backend on the PCA9685 emulator: the board must not see one transaction.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import policy_models
import pytest
from runner import JETBOT_RT, on_emulator

from jetbot_rt.runtime.policy import bundled_policy_path
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

MU = (1.0, -0.5)
PREVIOUS = '{"t":1.0,"event":"safe_stop","reason":"the crash to investigate"}\n'


def cli(tmp: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp / "run"))
    return subprocess.run([JETBOT_RT, *on_emulator(list(args), tmp / "chip.json")],
                          capture_output=True, text=True, timeout=60,
                          env=env, cwd=tmp)


def one_line(stderr: str, expected: str) -> None:
    assert "Traceback" not in stderr, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], stderr


@pytest.fixture
def setup(tmp_path: Path):
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    config = tmp_path / "robot.toml"
    config.write_text('[camera]\nsource = "gst:videotestsrc is-live=true"\n')
    chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    return tmp_path, policy, config, chip


def telemetry_alias(tmp: Path, target: Path, how: str) -> str:
    if how == "same-path":
        return str(target)
    if how == "relative":
        return f"./{target.name}"
    link = tmp / f"link-to-{target.name}"
    (link.symlink_to(target) if how == "symlink" else os.link(target, link))
    return str(link)


@pytest.mark.parametrize("victim", ["policy", "config"])
@pytest.mark.parametrize("how", ["same-path", "relative", "symlink", "hard-link"])
def test_telemetry_onto_the_policy_or_config_is_refused(setup, victim: str, how: str) -> None:
    tmp, policy, config, chip = setup
    target = policy if victim == "policy" else config
    before = target.read_bytes()
    result = cli(tmp, "run", "--backend", "real", "--policy", str(policy), "--config",
                 str(config), "--duration", "1", "--telemetry", telemetry_alias(tmp, target, how))
    assert result.returncode == 2, result.stdout + result.stderr
    one_line(result.stderr, f"is the --{victim} file")
    assert target.read_bytes() == before
    assert chip.refresh().transactions == 0


def test_telemetry_onto_the_bundled_policy_is_refused(setup) -> None:
    tmp, _policy, _config, _chip = setup
    bundled = bundled_policy_path()
    before = bundled.read_bytes()
    result = cli(tmp, "run", "--backend", "sim", "--duration", "1", "--telemetry", str(bundled))
    assert result.returncode == 2, result.stderr
    one_line(result.stderr, "is the --policy file")
    assert bundled.read_bytes() == before


@pytest.mark.parametrize("refusal", ["broken-model", "bad-flag-value", "board-absent"])
def test_a_refused_start_keeps_the_previous_telemetry(setup, refusal: str) -> None:
    tmp, policy, config, chip = setup
    telemetry = tmp / "t.jsonl"
    telemetry.write_text(PREVIOUS)
    args = ["run", "--backend", "real", "--policy", str(policy), "--config", str(config),
            "--duration", "1", "--telemetry", str(telemetry)]
    if refusal == "broken-model":
        policy.write_bytes(b"not a model")
        expected = str(policy)
    elif refusal == "bad-flag-value":
        args += ["--max-speed", "7"]
        expected = "--max-speed"
    else:
        chip.update(absent=True)
        expected = "no motor board"
    result = cli(tmp, *args)
    assert result.returncode == 2, result.stdout + result.stderr
    one_line(result.stderr, expected)
    text = telemetry.read_text()
    assert text.startswith(PREVIOUS), text  # the evidence is still there, first
    for line in text.splitlines()[1:]:
        assert json.loads(line)["exit_code"] == 2  # only the refusal's end record after it
    assert not (tmp / "t.jsonl.1").exists()
    assert chip.refresh().all_off()
    if refusal != "board-absent":
        assert chip.transactions == 0


def test_a_run_that_starts_moves_the_previous_telemetry_to_dot_1(tmp_path: Path) -> None:
    telemetry = tmp_path / "t.jsonl"
    telemetry.write_text(PREVIOUS)
    (tmp_path / "t.jsonl.1").write_text("older\n")
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    config = tmp_path / "slow.toml"  # a slow rate: this is about files, not a loaded machine
    config.write_text("[loop]\nrate_hz = 10\nwatchdog_timeout = 1.0\n")
    result = cli(tmp_path, "run", "--backend", "sim", "--policy", str(policy), "--duration",
                 "1", "--config", str(config), "--telemetry", str(telemetry))
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "t.jsonl.1").read_text() == PREVIOUS
    records = [json.loads(line) for line in telemetry.read_text().splitlines()]
    assert records[0]["event"] == "start" and records[-1]["event"] == "end"


@pytest.mark.parametrize(("args", "config_text", "expected"), [
    (["--policy", ""], "", "--policy: [policy] path must be a file name, not empty"),
    ([], '[policy]\npath = ""\n', "[policy] path must be a file name, not empty"),
    (["--telemetry", ""], "", "--telemetry: [telemetry] path must be a file name, not empty"),
    ([], '[telemetry]\npath = ""\n', "[telemetry] path must be a file name, not empty"),
])
def test_an_empty_path_is_an_error(setup, args, config_text, expected) -> None:
    tmp, _policy, config, chip = setup
    config.write_text(config.read_text() + config_text)
    result = cli(tmp, "run", "--backend", "real", "--config", str(config), "--duration", "1",
                 *args)
    assert result.returncode == 2, result.stdout + result.stderr
    one_line(result.stderr, expected)
    assert chip.refresh().transactions == 0


def test_check_with_an_empty_policy_is_an_error(setup) -> None:
    tmp, _policy, config, _chip = setup
    result = cli(tmp, "check", "--config", str(config), "--policy", "")
    assert result.returncode == 2, result.stdout + result.stderr
    one_line(result.stderr, "--policy must be a file name, not empty")
