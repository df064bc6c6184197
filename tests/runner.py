"""Run ``jetbot-rt`` as a user would: a subprocess of the installed console script."""

from __future__ import annotations

import itertools
import json
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

JETBOT_RT = shutil.which("jetbot-rt") or str(Path(sys.executable).parent / "jetbot-rt")
BOARD_COMMANDS = ("run", "check", "stop")
"""The subcommands that touch the motor board, so take ``--board-emulator``."""


def on_emulator(args: list[str], chip: Path | str) -> list[str]:
    """``args`` (a subcommand first) with the PCA9685 emulator in ``chip`` as the board, for
    the commands that touch one; others unchanged."""
    if args and args[0] in BOARD_COMMANDS:
        return [*args, "--board-emulator", str(chip)]
    return list(args)


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


# ---- fault-injection helpers (tests/test_fault_*.py) ----------------------------------------


def processes_with(marker: str) -> list[int]:
    """Pids of live (non-zombie) processes whose command line contains ``marker``: /proc only."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if marker in cmdline and state != "Z":
            found.append(int(entry.name))
    return found


def wait_for(predicate, timeout: float, interval: float = 0.005) -> float | None:
    """Poll ``predicate`` until true; the ``time.monotonic()`` at which it was seen, or None."""
    deadline = time.monotonic() + timeout
    while True:
        now = time.monotonic()
        if predicate():
            return now
        if now > deadline:
            return None
        time.sleep(interval)


def _no_core_dump() -> None:  # a SIGABRT test must not leave a core file behind
    import resource

    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


class RuntimeProcess:
    """One ``jetbot-rt run`` in a subprocess, isolated: its own control-socket directory and,
    for ``--backend real``, its own emulated PCA9685 (``self.chip``) shared through a file."""

    def __init__(self, root: Path, backend: str, policy: Path, *, config: str = "",
                 duration: float | None = 30.0, telemetry: Path | None = None,
                 extra_env: dict | None = None) -> None:
        import os

        from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

        self.root = root
        self.config = root / "config.toml"
        self.config.write_text(config)
        self.telemetry = root / "t.jsonl" if telemetry is None else telemetry
        self.args = ["run", "--backend", backend, "--policy", str(policy),
                     "--config", str(self.config), "--telemetry", str(self.telemetry)]
        if duration is not None:
            self.args += ["--duration", str(duration)]
        self.env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(root / "run"), **(extra_env or {}))
        self.env.pop("NOTIFY_SOCKET", None)
        self.env.pop("WATCHDOG_USEC", None)
        self.chip = None
        self.chip_file: Path | None = None
        if backend == "real":
            self.chip_file = root / "chip.json"
            self.chip = PCA9685Emulator(0x60, state_file=self.chip_file)
        self.process: subprocess.Popen[str] | None = None
        self.t_started = 0.0

    def start(self) -> RuntimeProcess:
        self.t_started = time.monotonic()
        self.process = subprocess.Popen([JETBOT_RT, *self.board(self.args)],
                                        stdout=subprocess.PIPE,
                                        stderr=subprocess.PIPE, text=True, env=self.env,
                                        cwd=self.root, preexec_fn=_no_core_dump)
        return self

    @property
    def pid(self) -> int:
        assert self.process is not None
        return self.process.pid

    def records(self) -> list[dict]:
        return read_telemetry_safe(self.telemetry)

    def tick_count(self) -> int:
        return sum(1 for r in self.records() if "event" not in r)

    def wait_ticks(self, count: int, timeout: float = 60.0) -> None:
        assert self.process is not None
        seen = wait_for(lambda: self.process.poll() is not None or self.tick_count() >= count,
                        timeout, interval=0.02)
        if seen is None or self.process.poll() is not None:
            out, err = self.finish_raw(10)
            raise AssertionError(f"fewer than {count} ticks (exit {self.process.returncode}):"
                                 f"\n{out}\n{err}")

    def board_off(self) -> bool:
        assert self.chip is not None
        return self.chip.refresh().all_off()

    def finish_raw(self, timeout: float = 60.0) -> tuple[str, str]:
        assert self.process is not None
        try:
            return self.process.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise

    def finish(self, timeout: float = 60.0) -> Result:
        out, err = self.finish_raw(timeout)
        assert self.process is not None
        records = read_telemetry_safe(self.telemetry) if self.telemetry.is_file() else []
        return Result(self.process.returncode, out, err, records)

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.communicate()

    def jetbot_rt(self, *args: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
        """Another ``jetbot-rt`` command in the same environment (``stop``: what systemd's
        ExecStopPost runs)."""
        return subprocess.run([JETBOT_RT, *self.board(list(args))], capture_output=True,
                              text=True, timeout=timeout, env=self.env)

    def board(self, args: list[str]) -> list[str]:
        """``args`` on this process's emulated board (``--board-emulator``), if it has one."""
        return args if self.chip_file is None else on_emulator(args, self.chip_file)


def assert_fixed_rate(ticks: list[dict], period: float) -> float:
    """Check the loop's schedule in tick records: deadlines ``t - late_ms`` are whole periods
    apart, every skipped deadline is counted in ``overruns``, and no tick starts less than half
    a period after the previous one (no burst to catch up). Returns the smallest gap (s)."""
    assert len(ticks) >= 2
    smallest = float("inf")
    for before, after in itertools.pairwise(ticks):
        smallest = min(smallest, after["t"] - before["t"])
        skipped = after["overruns"] - before["overruns"]
        deadline_step = ((after["t"] - after["late_ms"] / 1e3)
                         - (before["t"] - before["late_ms"] / 1e3))
        assert abs(deadline_step - period * (1 + skipped)) < 2e-3, (before, after)
    assert smallest >= period / 2, f"two ticks {smallest * 1e3:.1f} ms apart: a burst"
    return smallest
