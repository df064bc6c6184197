"""The service's end-to-end behaviour without systemd: the real CLI in a subprocess, a real
notify socket bound here as systemd would, the real sim or the register-level PCA9685 emulator.

- READY=1 after warm-up and before the first WATCHDOG=1; WATCHDOG=1 at least twice per
  WATCHDOG_USEC while driving; STATUS= lines; STOPPING=1 last.
- A tick that hangs inside onnxruntime ends the pings; the runtime's safe stop, exit code 3.
- After a SIGKILL (what systemd does after a watchdog timeout or a stop timeout) nothing of the
  runtime runs; ``jetbot-rt stop`` as ExecStopPost runs it turns the emulated board all off.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sysconfig
import threading
import time
import uuid
from itertools import pairwise
from pathlib import Path

import policy_models
import pytest

from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

JETBOT_RT = str(Path(sysconfig.get_path("scripts")) / "jetbot-rt")
RUN_TIMEOUT = 90  # seconds; a generous bound for a run of a few simulated seconds

pytestmark = pytest.mark.slow


class NotifyListener:
    """systemd's side of the notify socket: every datagram with its arrival time."""

    def __init__(self, name: str, address: str | bytes) -> None:
        self.name = name
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)
        self.sock.settimeout(0.1)
        self.messages: list[tuple[float, dict[str, str]]] = []
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    def _receive(self) -> None:
        while not self._done.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            fields = dict(line.split("=", 1) for line in data.decode().split("\n") if line)
            with self._lock:
                self.messages.append((time.monotonic(), fields))

    def wait_for(self, key: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if any(key in fields for _, fields in self.messages):
                    return True
            time.sleep(0.02)
        return False

    def close(self) -> list[tuple[float, dict[str, str]]]:
        time.sleep(0.2)  # let the last datagrams in
        self._done.set()
        self._thread.join()
        self.sock.close()
        return self.messages

    def times_of(self, key: str) -> list[float]:
        return [t for t, fields in self.messages if key in fields]


def path_listener(tmp_path: Path) -> NotifyListener:
    path = str(tmp_path / "notify.sock")
    return NotifyListener(path, path)


def abstract_listener() -> NotifyListener:
    name = f"jetbot-rt-e2e-{uuid.uuid4().hex}"
    return NotifyListener("@" + name, b"\0" + name.encode())


def service_env(listener: NotifyListener, watchdog_usec: int, runtime_dir: Path) -> dict[str, str]:
    """The environment systemd gives the unit's processes (no WATCHDOG_PID: it is optional)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JETBOT_RT_", "WATCHDOG"))}
    runtime_dir.mkdir(exist_ok=True)
    env.update(
        NOTIFY_SOCKET=listener.name,
        WATCHDOG_USEC=str(watchdog_usec),
        RUNTIME_DIRECTORY=str(runtime_dir),
    )
    return env


def jetbot_rt(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [JETBOT_RT, *args], env=env, capture_output=True, text=True, timeout=RUN_TIMEOUT
    )


def read_telemetry(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_ready_then_watchdog_twice_per_usec_in_a_sim_run(tmp_path: Path):
    policy = policy_models.constant(tmp_path / "forward.onnx", (0.5, 0.5))
    telemetry = tmp_path / "run.jsonl"
    listener = path_listener(tmp_path)
    watchdog_usec, duration = 1_000_000, 2.0
    env = service_env(listener, watchdog_usec, tmp_path / "run")
    # The pings are the point, not the loop's own 0.1 s watchdog, which a starved sim world on a
    # loaded host trips between ticks (safe, exit 3): 0.5 s still trips long before a 1 s gap.
    config = tmp_path / "patient.toml"
    config.write_text("[loop]\nwatchdog_timeout = 0.5\n")
    result = jetbot_rt(
        "run", "--backend", "sim", "--policy", str(policy), "--duration", str(duration),
        "--config", str(config), "--telemetry", str(telemetry), env=env,
    )
    messages = listener.close()
    assert result.returncode == 0, result.stderr

    keys = [fields for _, fields in messages]
    assert keys[0].get("READY") == "1", "READY=1 is the first message, before any WATCHDOG=1"
    assert sum("READY" in k for k in keys) == 1
    assert keys[-1].get("STOPPING") == "1", "STOPPING=1 is the last message"
    pings = listener.times_of("WATCHDOG")
    assert all(k["WATCHDOG"] == "1" for k in keys if "WATCHDOG" in k)
    # At least twice per WATCHDOG_USEC over the run; never a gap systemd would act on.
    assert len(pings) >= 2 * duration / (watchdog_usec / 1e6), pings
    assert max(b - a for a, b in pairwise(pings)) < watchdog_usec / 1e6
    ticks = [r for r in read_telemetry(telemetry) if "tick" in r and "event" not in r]
    assert len(pings) <= len(ticks) / 4, "a ping per interval, not one per tick"
    statuses = [k["STATUS"] for k in keys[1:-1] if "STATUS" in k]
    assert statuses and any("Hz" in s for s in statuses), statuses


def test_hung_tick_stops_the_pings_then_safe_stop(tmp_path: Path):
    policy = policy_models.hang_when_dark(tmp_path / "hang.onnx")
    config = tmp_path / "blackout.toml"
    config.write_text("[sim]\nblackout = [0.5, 100.0]\n")
    telemetry = tmp_path / "run.jsonl"
    listener = abstract_listener()
    env = service_env(listener, 300_000, tmp_path / "run")  # a ping every 0.1 s
    result = jetbot_rt(
        "run", "--backend", "sim", "--policy", str(policy), "--config", str(config),
        "--duration", "20", "--telemetry", str(telemetry), env=env,
    )
    messages = listener.close()
    assert result.returncode == 3, result.stdout + result.stderr

    keys = [fields for _, fields in messages]
    assert keys[0].get("READY") == "1"
    assert keys[-1].get("STOPPING") == "1"
    pings = listener.times_of("WATCHDOG")
    assert len(pings) >= 3, "it drove (and pinged) until the blackout at 0.5 s simulated time"
    # That no ping comes from anything but a completed tick is counted, not timed, in
    # TestWatchdogPingsComeFromCompletedTicks.
    records = read_telemetry(telemetry)
    [safe_stop] = [r for r in records if r.get("event") == "safe_stop"]
    assert "watchdog" in safe_stop["reason"] or "hung" in safe_stop["reason"], safe_stop
    [end] = [r for r in records if r.get("event") == "end"]
    assert end["exit_code"] == 3 and end["cmd"] == [0.0, 0.0]


@pytest.mark.skipif(shutil.which("gst-launch-1.0") is None, reason="needs gst-launch-1.0")
def test_stop_after_sigkill_turns_the_emulated_board_off(tmp_path: Path):
    policy = policy_models.constant(tmp_path / "forward.onnx", (1.0, 0.5))
    config = tmp_path / "robot.toml"
    config.write_text(
        '[camera]\nsource = "gst:videotestsrc is-live=true ! '
        'video/x-raw,width=320,height=240,framerate=30/1"\n'
    )
    board_file = tmp_path / "pca9685.json"
    listener = path_listener(tmp_path)
    env = service_env(listener, 1_000_000, tmp_path / "run")
    runtime = subprocess.Popen(
        [JETBOT_RT, "run", "--backend", "real", "--policy", str(policy),
         "--config", str(config), "--duration", "60", "--board-emulator", str(board_file)],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        start_new_session=True,  # its own process group, like the unit's cgroup
    )
    try:
        driving = listener.wait_for("WATCHDOG", timeout=RUN_TIMEOUT)
        assert driving, "no WATCHDOG=1: the runtime never completed a tick"
        time.sleep(0.3)
        # systemd's final kill: SIGKILL to every process of the unit; no handler runs.
        os.killpg(runtime.pid, signal.SIGKILL)
        runtime.wait(timeout=10)
    finally:
        if runtime.poll() is None:
            os.killpg(runtime.pid, signal.SIGKILL)
            runtime.wait()
    messages = listener.close()
    assert runtime.returncode == -signal.SIGKILL, runtime.stderr.read() if runtime.stderr else ""
    assert not any("STOPPING" in fields for _, fields in messages), "it died, it did not stop"
    board = PCA9685Emulator(state_file=board_file).refresh()
    assert not board.all_off(), f"the killed runtime left the motors driving: {board.duties()}"

    # ExecStopPost: same environment as the unit's ExecStart, the stale control socket left.
    result = jetbot_rt("stop", "--config", str(config), "--board-emulator", str(board_file),
                       env=env)
    assert result.returncode == 0, result.stdout + result.stderr
    board = PCA9685Emulator(state_file=board_file).refresh()
    assert board.all_off(), board.duties()



class TestWatchdogPingsComeFromCompletedTicks:
    """systemd's WATCHDOG=1 must prove the loop ticks, not that the process lives. With an
    in-process watchdog_timeout many ping intervals long, a loop stuck in onnxruntime must
    still stop the pings at once: every ping is paid for by a completed tick."""

    def test_a_stuck_loop_stops_the_pings_before_the_runtime_watchdog_acts(
            self, tmp_path: Path) -> None:
        policy = policy_models.hang_when_dark(tmp_path / "hang.onnx")
        config = tmp_path / "robot.toml"
        config.write_text("[loop]\nwatchdog_timeout = 1.0\n[sim]\nblackout = [0.5, 100.0]\n")
        telemetry = tmp_path / "run.jsonl"
        listener = abstract_listener()
        watchdog_usec = 150_000  # a ping due every 0.05 s: 20 intervals within the timeout
        interval = watchdog_usec / 1e6 / 3
        env = service_env(listener, watchdog_usec, tmp_path / "run")
        result = jetbot_rt(
            "run", "--backend", "sim", "--policy", str(policy), "--config", str(config),
            "--duration", "30", "--telemetry", str(telemetry), env=env,
        )
        listener.close()
        assert result.returncode == 3, result.stdout + result.stderr
        records = read_telemetry(telemetry)
        [safe_stop] = [r for r in records if r.get("event") == "safe_stop"]
        assert safe_stop["reason"].startswith("watchdog"), safe_stop
        ticks = [r for r in records if "event" not in r]
        assert len(ticks) >= 5, "it drove until the blackout"
        pings = listener.times_of("WATCHDOG")
        assert pings, "a completed tick after READY=1 pings at once"
        # Pings go out after completed ticks, at most one per interval of the loop's own clock:
        # never more than the ticks' span (first start to last end) allows.
        span = ticks[-1]["t"] + ticks[-1]["tick_ms"] / 1e3 - ticks[0]["t"]
        assert len(pings) <= 1 + span / interval + 1, (len(pings), span, len(ticks))
        assert len(pings) <= len(ticks)
