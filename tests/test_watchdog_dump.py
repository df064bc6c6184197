"""systemd's watchdog ending a run: every thread's stack reaches stderr (the journal) every time,
and reading them never crashes the process (docs/SAFETY.md, "Untrusted input and sure exits").

The test plays systemd's part with the unit's own settings: ``WatchdogSignal=`` together with
SIGCONT (systemd sends SIGCONT after every signal but SIGKILL), then, if the process is still
there ``TimeoutAbortSec=`` later, ``FinalKillSignal=`` with SIGCONT.

Two ways a service misses its pings, each repeated, with stderr read slowly (a busy journald:
the longer a dump takes, the longer another thread has to change what it reads):

- stopped (SIGSTOP: a debugger, ``kill -STOP``), then resumed by systemd's SIGCONT: every
  thread runs again at once. faulthandler's dump from a C signal handler raced them (SIGSEGV
  in 3 of 6 trials under systemd; 7 of 8 in the churning process below);
- wedged: a native call holds the GIL for ever, no Python code runs again.
"""

from __future__ import annotations

import fcntl
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import policy_models
import pytest
from fault_helpers import MU, assert_no_gst_left, live_camera, real_config
from runner import RuntimeProcess, read_telemetry_safe, wait_for

from jetbot_rt.commands import install_service
from jetbot_rt.service import signals

TESTS = Path(__file__).resolve().parent
F_SETPIPE_SZ = 1031


def unit_setting(key: str) -> str:
    [value] = re.findall(rf"^{key}=(.*)$", install_service.unit_template(), flags=re.MULTILINE)
    return value


def seconds(value: str) -> float:
    """A systemd time span of the forms the unit uses: ``1s``, ``500ms``, ``2``."""
    match = re.fullmatch(r"(\d+(?:\.\d+)?)(ms|s)?", value)
    assert match is not None, value
    return float(match.group(1)) / (1000 if match.group(2) == "ms" else 1)


WATCHDOG_SIGNAL = signal.Signals[unit_setting("WatchdogSignal")]
FINAL_KILL_SIGNAL = signal.Signals[unit_setting("FinalKillSignal")]
ABORT_S = seconds(unit_setting("TimeoutAbortSec"))


def test_the_unit_and_the_runtime_agree_on_the_signals() -> None:
    """The runtime prints the stacks on the signal the unit sends, and the final signal is one
    faulthandler handles (it prints every thread, then the process dies)."""
    assert WATCHDOG_SIGNAL == signals.WATCHDOG
    assert WATCHDOG_SIGNAL in signals.FAULTING and WATCHDOG_SIGNAL in signals.HANDLED
    assert FINAL_KILL_SIGNAL == signal.SIGABRT and FINAL_KILL_SIGNAL not in signals.HANDLED
    assert seconds(unit_setting("TimeoutStopSec")) > ABORT_S


class SlowReader:
    """stderr through a 4 KiB pipe read 64 bytes every 2 ms: a dump takes a while to leave."""

    def __init__(self) -> None:
        self.read_fd, self.write_fd = os.pipe()
        fcntl.fcntl(self.read_fd, F_SETPIPE_SZ, 4096)
        self.chunks: list[bytes] = []
        self.thread = threading.Thread(target=self._read, daemon=True)

    def start(self) -> None:
        os.close(self.write_fd)
        self.thread.start()

    def _read(self) -> None:
        while True:
            time.sleep(0.002)
            data = os.read(self.read_fd, 64)
            if not data:
                os.close(self.read_fd)
                return
            self.chunks.append(data)

    def text(self) -> str:
        self.thread.join(30)
        return b"".join(self.chunks).decode(errors="replace")


PATIENT_S = 20.0
"""How long a test that expects the Python handler waits before the final signal, instead of
``TimeoutAbortSec``: on a loaded host the main thread may need longer to run, and these tests
are about what is printed, not how fast (benchmarks/bench_stack_dump.py keeps the unit's 1 s)."""


def play_the_watchdog(process: subprocess.Popen, abort_after: float = ABORT_S,
                      first: int = WATCHDOG_SIGNAL) -> None:
    """What systemd does when the pings stop: the watchdog signal (``first``), then, if the
    process is still there ``abort_after`` s later, the final one; each with SIGCONT."""
    os.kill(process.pid, first)
    os.kill(process.pid, signal.SIGCONT)
    try:
        process.wait(abort_after)
    except subprocess.TimeoutExpired:
        os.kill(process.pid, FINAL_KILL_SIGNAL)
        os.kill(process.pid, signal.SIGCONT)
        process.wait(30)


def watchdog_ends(process: subprocess.Popen, reader: SlowReader, *,
                  stopped_for: float | None = None, **play: Any) -> str:
    """Stop the process for ``stopped_for`` s if given, play the watchdog; its stderr."""
    try:
        if stopped_for is not None:
            os.kill(process.pid, signal.SIGSTOP)
            time.sleep(stopped_for)
        if process.poll() is None:  # one that ended already fails the caller's assertions
            play_the_watchdog(process, **play)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    return reader.text()


def no_core_dump() -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


# ---- a process built to lose the race: threads that churn their stacks --------------------

CHURNING = """
import random, signal, sys, threading, time
from jetbot_rt.service import signals
sys.setrecursionlimit(5000)
random.seed(int(sys.argv[2]))

def churn(depth, limit):  # deep enough to leave and re-enter the frame stack's memory chunks
    if depth < limit:
        churn(depth + 1, limit)

def churner():
    while True:
        churn(0, random.randrange(50, 1500))

def spawner():  # thread states created and freed all the time
    while True:
        t = threading.Thread(target=churn, args=(0, 300))
        t.start()
        t.join()

def wedge():  # a native call that holds the GIL and that no signal interrupts
    import ctypes
    time.sleep(0.3)
    signal.pthread_sigmask(signal.SIG_BLOCK, signal.valid_signals())
    print("wedging", flush=True)
    ctypes.pythonapi.sleep(3600)

stopped = threading.Event()
signals.enable_stack_dumps()
signals.install(lambda signum, frame: stopped.set())
for _ in range(2):
    threading.Thread(target=churner, name="churner", daemon=True).start()
threading.Thread(target=spawner, name="spawner", daemon=True).start()
if sys.argv[1] == "wedged":
    threading.Thread(target=wedge, name="wedger", daemon=True).start()
print("ready", flush=True)
while not stopped.wait(0.05):
    pass
sys.exit(3)
"""


def churning_process(how: str, seed: int) -> tuple[subprocess.Popen, SlowReader]:
    reader = SlowReader()
    process = subprocess.Popen([sys.executable, "-c", CHURNING, how, str(seed)],
                               stdout=subprocess.PIPE, stderr=reader.write_fd, text=True,
                               preexec_fn=no_core_dump)
    reader.start()
    assert process.stdout is not None and process.stdout.readline() == "ready\n"
    return process, reader


@pytest.mark.parametrize("seed", range(6))
def test_a_stopped_process_resumed_by_the_watchdog_signal_prints_every_stack(seed: int) -> None:
    process, reader = churning_process("stopped", seed)
    time.sleep(0.2)
    err = watchdog_ends(process, reader, stopped_for=0.3, abort_after=PATIENT_S)
    assert process.returncode == 3, f"exit {process.returncode} (-11: SIGSEGV)\n{err[-2000:]}"
    assert "systemd's WatchdogSignal" in err
    threads = re.findall(r"^Thread (\S+) 0x", err, flags=re.MULTILINE)
    assert threads.count("churner") == 2 and "spawner" in threads and "MainThread" in threads
    assert "Fatal Python error" not in err, "the final signal was needed: Python did not run"


@pytest.mark.parametrize("seed", range(3))
def test_a_process_wedged_holding_the_gil_prints_every_stack_at_the_final_signal(
        seed: int) -> None:
    process, reader = churning_process("wedged", seed)
    assert process.stdout is not None and process.stdout.readline() == "wedging\n"
    time.sleep(0.2)  # a few bytecodes from the print to the native call: the load decides when
    # the wedge began, so the test waits for it to say so instead of a fixed time from start
    err = watchdog_ends(process, reader)
    assert process.returncode == -signal.SIGABRT, f"exit {process.returncode}\n{err[-2000:]}"
    assert "Fatal Python error: Aborted" in err
    assert re.search(r'line \d+ in wedge\n', err), err[-2000:]
    assert err.count("most recent call first") >= 4, "every thread, not one"


# ---- the runtime itself --------------------------------------------------------------------

needs_gst = pytest.mark.skipif(shutil.which("gst-launch-1.0") is None,
                               reason="needs gst-launch-1.0")


@needs_gst
@pytest.mark.parametrize("attempt", range(2))
def test_a_stopped_runtime_resumed_by_the_watchdog_signal_stops_the_motors_and_every_stack(
        tmp_path: Path, attempt: int) -> None:
    mark = f"wd{os.getpid()}x{attempt}"
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    rt = RuntimeProcess(tmp_path, "real", policy, config=real_config(live_camera(mark)))
    try:
        rt.start()
        rt.wait_ticks(10)
        assert not rt.board_off(), "it was driving"
        os.kill(rt.pid, signal.SIGSTOP)
        time.sleep(0.3)
        assert rt.process is not None
        play_the_watchdog(rt.process, abort_after=PATIENT_S)
        result = rt.finish(30)
    finally:
        rt.kill()
    assert result.returncode == 3, result.stdout + result.stderr
    assert "systemd's WatchdogSignal" in result.stderr
    # Resumed, the runtime's own watchdog sees the gap and the loop may end before the main
    # thread handles the signal: the threads that live until the exit are there.
    threads = re.findall(r"^Thread (\S+) 0x", result.stderr, flags=re.MULTILINE)
    assert {"MainThread", "jetbot-rt-control", "gst-camera-frames"} <= set(threads), threads
    assert "Fatal Python error" not in result.stderr
    # A fault whichever saw it first: the watchdog signal, or, resumed, the runtime's own
    # watchdog or its frame-age check.
    (stop,) = result.events("safe_stop")
    assert stop["fault"] is True, stop
    assert result.records[-1]["event"] == "end" and result.records[-1]["cmd"] == [0.0, 0.0]
    assert rt.board_off(), rt.chip.duties() if rt.chip else None
    assert_no_gst_left(mark)


@pytest.mark.parametrize("attempt", range(2))
def test_a_runtime_wedged_holding_the_gil_prints_every_stack_at_the_final_signal(
        tmp_path: Path, attempt: int) -> None:
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    telemetry = tmp_path / "run.jsonl"
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
    env["JETBOT_RT_RUNTIME_DIR"] = str(tmp_path / "run")
    # Patient thresholds: under a loaded CI host the 0.1 s watchdog could trip before the
    # wedge, and this case is about a process in which no Python runs any more.
    config = tmp_path / "patient.toml"
    config.write_text("[loop]\nwatchdog_timeout = 2.0\nmax_frame_age = 2.0\n")
    reader = SlowReader()
    process = subprocess.Popen(
        [sys.executable, str(TESTS / "wedge_backend.py"), "run", "--backend", "wedge",
         "--policy", str(policy), "--duration", "60", "--telemetry", str(telemetry),
         "--config", str(config)],
        stdout=subprocess.DEVNULL, stderr=reader.write_fd, env=env, cwd=tmp_path,
        preexec_fn=no_core_dump)
    reader.start()

    def ticks() -> int:
        return sum(1 for r in read_telemetry_safe(telemetry) if "event" not in r)

    seen = [0]

    def stalled() -> bool:  # no tick for 0.5 s: wedged, the runtime's watchdog with it
        seen.append(ticks())
        return len(seen) > 10 and seen[-1] >= 5 and seen[-1] == seen[-11]

    try:
        assert wait_for(lambda: process.poll() is not None or stalled(), 60, 0.05) is not None
        events = [r for r in read_telemetry_safe(telemetry) if "event" in r]
        assert process.poll() is None, f"it ended: the runtime acted, not wedged: {events}"
    finally:
        err = watchdog_ends(process, reader)
    assert process.returncode == -signal.SIGABRT, f"exit {process.returncode}\n{err[-3000:]}"
    assert "Fatal Python error: Aborted" in err
    assert "wedge_backend.py" in err and "in wedge_holding_the_gil" in err, err[-3000:]
    assert "jetbot_rt/runtime/loop.py" in err and "jetbot_rt/runtime/safety.py" in err, \
        "every thread"
    assert not [r for r in read_telemetry_safe(telemetry) if r.get("event") == "end"], \
        "nothing of the runtime ran after the wedge (ExecStopPost's case)"
