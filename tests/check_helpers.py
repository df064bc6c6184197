"""``jetbot-rt check`` as a subprocess, for the tests that run it: a robot directory with a
constant policy (conftest's ``robot`` fixture), its config, the command and its output's rows."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from jetbot_rt.hal.i2c import EMULATOR_FLAG


def write_config(robot: Path, source: str, fps: float = 30) -> Path:
    config = robot / "robot.toml"
    config.write_text(f'[camera]\nsource = "{source}"\nfps = {fps}\nstart_timeout = 5\n'
                      "[motors]\ni2c_retries = 1\n")
    return config


def check(robot: Path, config: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(robot / "run"))
    return subprocess.run(
        [sys.executable, "-m", "jetbot_rt.cli", "check", "--config", str(config),
         EMULATOR_FLAG, str(robot / "chip.json"),
         "--policy", str(robot / "policy.onnx"), "--frames", "10", *args],
        capture_output=True, text=True, timeout=60, env=env,
    )


def rows(output: str) -> dict[str, str]:
    return {line.split()[0]: line for line in output.splitlines() if line.strip()}
