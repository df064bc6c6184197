"""No print, log or telemetry write blocks the control thread, a signal's handling or the exit:
``jetbot-rt run`` with a stdout, a stderr or a telemetry FIFO that nobody reads (a pipe filled
to the brim first, as a stalled journald or a terminal stopped with Ctrl-S would be) still
drives, stops on SIGTERM, SIGINT or ``jetbot-rt stop`` with the motors at zero, and exits.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import policy_models
import pytest
from fault_helpers import record_figures
from runner import JETBOT_RT, RuntimeProcess, read_telemetry, read_telemetry_safe, wait_for

LIVENESS_S = 60.0
"""How long a run may take to end once told to (only catches a hang; never a timing)."""
PATIENT = "[loop]\nwatchdog_timeout = 1.0\nmax_frame_age = 1.0\n"
"""These runs are about the output, not about the watchdog on a loaded host."""


@contextlib.contextmanager
def full_pipe() -> Iterator[int]:
    """A pipe's write end (blocking, as a child gets it) whose buffer is already full; the read
    end stays open and is never read, so a write blocks instead of failing with EPIPE."""
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    chunk = b"x" * 65536
    with contextlib.suppress(BlockingIOError):
        while True:
            os.write(write_end, chunk)
    with contextlib.suppress(BlockingIOError):
        while True:
            os.write(write_end, b"x")
    os.set_blocking(write_end, True)
    try:
        yield write_end
    finally:
        os.close(write_end)
        os.close(read_end)


def start_run(tmp_path: Path, stdout: int, stderr: int, *extra: str,
              duration: float = 120.0) -> subprocess.Popen[bytes]:
    policy = policy_models.constant(tmp_path / "p.onnx", (1.0, 1.0))
    config = tmp_path / "config.toml"
    config.write_text(PATIENT)
    return subprocess.Popen(
        [JETBOT_RT, "run", "--backend", "sim", "--policy", str(policy), "--config", str(config),
         "--duration", str(duration), "--telemetry", str(tmp_path / "t.jsonl"), *extra],
        stdout=stdout, stderr=stderr, env=dict(os.environ),
    )


def ticks(tmp_path: Path) -> int:
    return sum(1 for r in read_telemetry_safe(tmp_path / "t.jsonl") if "event" not in r)


def ended(process: subprocess.Popen[bytes]) -> int:
    try:
        return process.wait(LIVENESS_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        raise AssertionError("the run hung on its output") from None


def stop_command(tmp_path: Path, process: subprocess.Popen[bytes]) -> None:
    with full_pipe() as stalled:  # stop's own output is stalled too
        done = subprocess.run([JETBOT_RT, "stop"], stdout=stalled, stderr=stalled,
                              timeout=LIVENESS_S)
    assert done.returncode == 1  # on the sim there is no board for its second step


ENDERS = {
    "SIGTERM": lambda tmp_path, process: process.send_signal(signal.SIGTERM),
    "SIGINT": lambda tmp_path, process: process.send_signal(signal.SIGINT),
    "jetbot-rt stop": stop_command,
}
REASONS = {"SIGTERM": "SIGTERM received", "SIGINT": "SIGINT received",
           "jetbot-rt stop": "jetbot-rt stop from pid"}


@pytest.mark.parametrize(("stalled", "ender"), [("stdout", "SIGTERM"), ("stderr", "SIGINT"),
                                                 ("both", "jetbot-rt stop")])
def test_a_run_whose_output_nobody_reads_drives_and_stops(tmp_path: Path, stalled: str,
                                                          ender: str) -> None:
    log = open(tmp_path / "other.log", "wb")  # noqa: SIM115 - closed below
    with full_pipe() as pipe, log:
        stdout = pipe if stalled in ("stdout", "both") else log.fileno()
        stderr = pipe if stalled in ("stderr", "both") else log.fileno()
        process = start_run(tmp_path, stdout, stderr)
        try:
            # past its "driving at ..." line: it drives
            seen = wait_for(lambda: process.poll() is not None or ticks(tmp_path) >= 15,
                            LIVENESS_S, interval=0.05)
            assert seen is not None and process.poll() is None, "it did not drive"
            t_told = time.monotonic()
            ENDERS[ender](tmp_path, process)
            code = ended(process)
            t_exit = time.monotonic()
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    assert code == 0
    end = read_telemetry(tmp_path / "t.jsonl")[-1]
    assert end["event"] == "end" and end["reason"].startswith(REASONS[ender]), end
    assert end["cmd"] == [0.0, 0.0] and end["motors_confirmed_zero"] is True
    record_figures(f"stalled-{stalled}-{ender.replace(' ', '-')}", exit_code=code,
                   told_to_exit_s=round(t_exit - t_told, 4), ticks=end["ticks"])


def test_a_run_that_ends_by_itself_leaves_though_nobody_reads_its_summary(
        tmp_path: Path) -> None:
    with full_pipe() as pipe:
        process = start_run(tmp_path, pipe, pipe, duration=1.0)
        code = ended(process)
    assert code == 0
    end = read_telemetry(tmp_path / "t.jsonl")[-1]
    assert end["event"] == "end" and end["reason"] == "duration 1 s reached"


def test_bad_input_whose_one_line_nobody_reads_still_exits_2(tmp_path: Path) -> None:
    with full_pipe() as pipe:
        process = subprocess.Popen([JETBOT_RT, "run", "--backend", "sim", "--rate", "0"],
                                   stdout=pipe, stderr=pipe)
        assert ended(process) == 2


def test_the_streams_are_given_back_when_the_command_is_done(tmp_path: Path) -> None:
    """In one process (as a test or an embedding program runs it): after ``main`` returns,
    ``sys.stdout`` and ``sys.stderr`` are the interpreter's own again, everything written."""
    code = ("import sys\nfrom jetbot_rt import cli\nfrom jetbot_rt.service import console\n"
            "code = cli.main(['run', '--backend', 'sim', '--rate', '0'])\n"
            "assert sys.stdout is sys.__stdout__ and sys.stderr is sys.__stderr__\n"
            "assert not isinstance(sys.stdout, console.NonBlockingStream)\n"
            "print('after', code)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=LIVENESS_S)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "after 2\n"
    (line,) = done.stderr.splitlines()
    assert line.startswith("jetbot-rt run: error: --rate: [loop] rate_hz must be")


BUG = ("from jetbot_rt.service import console\n"
       "with console.unblocked():\n"
       "    print('before')\n"
       "    raise RuntimeError('a bug')\n")


def test_a_bugs_traceback_reaches_a_reader_and_blocks_no_exit_without_one() -> None:
    """A traceback is printed by the interpreter after the command has returned: through the
    same non-blocking streams, drained (bounded) at the exit."""
    shown = subprocess.run([sys.executable, "-c", BUG], capture_output=True, text=True,
                           timeout=LIVENESS_S)
    assert shown.returncode == 1 and shown.stdout == "before\n"
    assert shown.stderr.rstrip().endswith("RuntimeError: a bug"), shown.stderr
    with full_pipe() as pipe:
        process = subprocess.Popen([sys.executable, "-c", BUG], stdout=pipe, stderr=pipe)
        assert ended(process) == 1


@pytest.mark.skipif(shutil.which("gst-launch-1.0") is None, reason="needs gst-launch-1.0")
def test_a_telemetry_fifo_nobody_reads_costs_records_not_the_stop(tmp_path: Path) -> None:
    mark = f"so{uuid.uuid4().hex[:12]}"
    fifo = tmp_path / "telemetry.fifo"
    os.mkfifo(fifo)
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # opened, never read
    filler = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
    with contextlib.suppress(BlockingIOError):
        while True:
            os.write(filler, b"{}\n" * 1024)
    os.close(filler)
    policy = policy_models.constant(tmp_path / "p.onnx", (1.0, 1.0))
    config = (f'[camera]\nsource = "gst:videotestsrc name={mark} is-live=true"\n'
              f"start_timeout = 10\n{PATIENT}")
    rt = RuntimeProcess(tmp_path, "real", policy, config=config, telemetry=fifo, duration=None)
    try:
        rt.start()  # its telemetry cannot be read here: the board says when it drives
        driving = wait_for(lambda: rt.process.poll() is not None or not rt.board_off(),
                           LIVENESS_S, interval=0.05)
        assert driving is not None and rt.process.poll() is None, "it did not drive"
        t_signal = time.monotonic()
        os.kill(rt.pid, signal.SIGTERM)
        t_off = wait_for(rt.board_off, LIVENESS_S)
        result = rt.finish(LIVENESS_S)
        t_exit = time.monotonic()
    finally:
        rt.kill()
        os.close(reader)
    assert result.returncode == 0, result.stdout + result.stderr
    assert rt.board_off() and t_off is not None
    assert "stopped      SIGTERM received" in result.stdout
    assert "motors       confirmed zero" in result.stdout
    assert "the writer is blocked" in result.stderr
    assert "Traceback" not in result.stderr
    record_figures("stalled-telemetry-fifo-real", exit_code=result.returncode,
                   inject_to_board_off_s=round(t_off - t_signal, 4),
                   told_to_exit_s=round(t_exit - t_signal, 4))
