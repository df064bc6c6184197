"""Run ``jetbot-rt`` as a user would: a subprocess of the installed console script."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

JETBOT_RT = shutil.which("jetbot-rt") or str(Path(sys.executable).parent / "jetbot-rt")


@dataclass
class Result:
    returncode: int
    stdout: str
    stderr: str
    records: list[dict]

    @property
    def ticks(self) -> list[dict]:
        return [r for r in self.records if "event" not in r]

    def events(self, name: str) -> list[dict]:
        return [r for r in self.records if r.get("event") == name]


def read_telemetry(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def run_cli(args: list[str], telemetry: Path | None = None, timeout: float = 60.0,
            env: dict | None = None) -> Result:
    cmd = [JETBOT_RT, *args]
    if telemetry is not None:
        cmd += ["--telemetry", str(telemetry)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    records = read_telemetry(telemetry) if telemetry else []
    return Result(proc.returncode, proc.stdout, proc.stderr, records)


def run_until(args: list[str], telemetry: Path, *, ticks: int, sig: int = signal.SIGTERM,
              timeout: float = 60.0, env: dict | None = None) -> Result:
    """Start a run, wait for ``ticks`` tick records, send ``sig``, wait for the exit."""
    proc = subprocess.Popen([JETBOT_RT, *args, "--telemetry", str(telemetry)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if sum(1 for r in read_telemetry_safe(telemetry) if "event" not in r) >= ticks:
                break
            time.sleep(0.05)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return Result(proc.returncode, stdout, stderr, read_telemetry(telemetry))


def read_telemetry_safe(path: Path) -> list[dict]:
    """Like read_telemetry, but tolerates a half-written last line of a running process."""
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return records
