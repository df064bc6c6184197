"""Fault matrix, who drives the board (classes 2 and 3; docs/SAFETY.md, "What a stop
guarantees").

- ``jetbot-rt stop`` defeats a runtime it cannot talk to (another runtime directory, no
  socket at all): its stop puts the PCA9685 to SLEEP after turning every output off, the
  runtime's next write finds the chip asleep, which is a fault (exit 3); ``stop`` reports
  success only once no process owns the bus and the chip still sleeps.
- One owner per bus: a second ``run --backend real`` or a ``check --spin`` is refused (exit
  2, naming the owner's pid) whatever its environment; of two runtimes started at the same
  moment exactly one drives; simulations own no board and run side by side.

The real CLI in subprocesses, the real backend on the register-level PCA9685 emulator and a
``videotestsrc`` camera; the board state is read from the emulator.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import policy_models
import pytest
from fault_helpers import (
    MU,
    assert_no_gst_left,
    live_camera,
    needs_gst,
    real_config,
    record_figures,
)
from runner import JETBOT_RT, RuntimeProcess, on_emulator, processes_with, wait_for

OFF_AFTER_STOP_S = 10.0
"""Bound asserted on: ``jetbot-rt stop`` started -> every output of the board off (an
interpreter start on a loaded machine; measured figures in docs/SAFETY.md)."""
LOOP = "[loop]\nwatchdog_timeout = 0.5\nmax_frame_age = 0.5\n"
"""These cases are about who drives, not the watchdog: generous thresholds keep a loaded
machine (a stop's interpreter start next to the runtime) from ending a run for another cause."""
ASLEEP = "is asleep: stopped by another process (jetbot-rt stop) or reset"


def start_real(tmp: Path, **kwargs) -> tuple[RuntimeProcess, str]:
    mark = f"fm{uuid.uuid4().hex[:12]}"
    policy = policy_models.constant(tmp / "policy.onnx", MU)
    rt = RuntimeProcess(tmp, "real", policy, config=real_config(live_camera(mark)) + LOOP,
                        **kwargs)
    return rt.start(), mark


def stop_in(rt: RuntimeProcess, env: dict) -> tuple[subprocess.Popen, float]:
    proc = subprocess.Popen([JETBOT_RT, *on_emulator(["stop"], rt.chip_file)],
                            stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    return proc, time.monotonic()


def one_line(stderr: str) -> str:
    assert "Traceback" not in stderr, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


def env_without_runtime_dirs(rt: RuntimeProcess, **extra: str) -> dict:
    env = {k: v for k, v in rt.env.items()
           if k not in ("JETBOT_RT_RUNTIME_DIR", "RUNTIME_DIRECTORY", "XDG_RUNTIME_DIR")}
    return dict(env, **extra)


# ---- class 2: a stop that works whatever the environment of the sender --------------------

STOP_ENVS = {  # (only XDG_RUNTIME_DIR set: where stop looks then is tests/test_stop.py's)
    "other-JETBOT_RT_RUNTIME_DIR": lambda rt: dict(
        rt.env, JETBOT_RT_RUNTIME_DIR=str(rt.root / "elsewhere")),
    "RUNTIME_DIRECTORY-only": lambda rt: env_without_runtime_dirs(
        rt, RUNTIME_DIRECTORY=str(rt.root / "systemd")),
    "socket-file-removed": None,
}


@needs_gst
@pytest.mark.parametrize("variant", list(STOP_ENVS))
def test_stop_defeats_a_runtime_it_cannot_talk_to(tmp_path: Path, variant: str) -> None:
    rt, mark = start_real(tmp_path)
    try:
        rt.wait_ticks(15)
        assert not rt.board_off()
        if variant == "socket-file-removed":
            (sock,) = (rt.root / "run").glob("control-*.sock")
            sock.unlink()
            env = rt.env
        else:
            env = STOP_ENVS[variant](rt)
        stop, t0 = stop_in(rt, env)
        t_off = wait_for(rt.board_off, OFF_AFTER_STOP_S)
        out, err = stop.communicate(timeout=30)
        t_reported = time.monotonic()
        result = rt.finish(30)
    finally:
        rt.kill()
    assert t_off is not None, "the board was not turned off"
    assert stop.returncode == 0, out + err
    assert "motor outputs off" in out and "latched" not in out
    assert "Traceback" not in err
    # The runtime that did not hear the stop faulted at its next write, and is gone.
    assert result.returncode == 3, result.stdout + result.stderr
    assert "Traceback" not in result.stderr
    end = result.records[-1]
    assert end["event"] == "end" and ASLEEP in end["reason"], end
    assert rt.board_off() and rt.chip.sleeping
    assert_no_gst_left(mark)
    record_figures(f"stop-unreachable-{variant}-real", exit_code=result.returncode,
                   stop_to_board_off_s=round(t_off - t0, 4),
                   stop_to_reported_s=round(t_reported - t0, 4))


MOMENTS = {
    # the runtime has set the board up (chip awake, all off) and is warming up its policy
    "during-warm-up": lambda rt: not rt.chip.refresh().sleeping,
    "first-command": lambda rt: not rt.board_off(),
    "driving": lambda rt: rt.tick_count() >= 15,
}


@needs_gst
@pytest.mark.parametrize("moment", list(MOMENTS))
def test_stop_never_reports_success_while_a_runtime_drives(tmp_path: Path, moment: str) -> None:
    """A stop from another environment (it cannot reach the runtime's socket) at several
    moments of a runtime's life once it owns the board. ``stop`` waits until the runtime has
    ended (it faults at its first write to the sleeping chip); if it says 0, the board was off
    then and nothing drove it after."""
    rt, mark = start_real(tmp_path)
    env = dict(rt.env, JETBOT_RT_RUNTIME_DIR=str(rt.root / "elsewhere"))
    try:
        assert wait_for(lambda: rt.process.poll() is not None or MOMENTS[moment](rt), 60.0,
                        0.002) is not None
        t0 = time.monotonic()
        stop = subprocess.run([JETBOT_RT, *on_emulator(["stop"], rt.chip_file)],
                              capture_output=True, text=True, env=env, timeout=30)
        t_reported = time.monotonic()
        reported_off = rt.board_off()
        runtime_gone = rt.process.poll() is not None
        driven_after = wait_for(lambda: not rt.board_off(), 1.0, 0.01) is not None
        result = rt.finish(30)
    finally:
        rt.kill()
    assert stop.returncode == 0, stop.stdout + stop.stderr
    assert "Traceback" not in stop.stderr
    assert reported_off and not driven_after, "stop said off while a runtime drove"
    assert runtime_gone or wait_for(lambda: rt.process.poll() is not None, 0) is not None
    assert result.returncode == 3, result.stdout + result.stderr
    assert ASLEEP in result.records[-1]["reason"]  # its first write after the stop
    assert "Traceback" not in result.stderr
    assert rt.board_off() and rt.chip.sleeping
    assert_no_gst_left(mark)
    record_figures(f"stop-while-{moment}-real", exit_code=result.returncode,
                   stop_to_reported_s=round(t_reported - t0, 4))


HOLDER = """
import fcntl, os, sys, time
from jetbot_rt.hal.i2c import I2CBus
from jetbot_rt.hal.motors import MODE1, MODE1_AI, WaveshareDrive
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator
lock = os.open(sys.argv[1] + ".owner", os.O_RDONLY | os.O_CREAT, 0o666)
fcntl.flock(lock, fcntl.LOCK_EX)
bus = I2CBus(PCA9685Emulator(0x60, state_file=sys.argv[1]), 1)
drive = WaveshareDrive(bus, 0x60, 1600.0)
print("ready", flush=True)
while True:
    if sys.argv[2] == "wakes":  # an old program: sets the chip up again before each write
        bus.writeto(0x60, bytes((MODE1, MODE1_AI)))
        bus.writeto(0x60, bytes((0x06, 0, 0, 0x9A, 0x01) * 2))
    time.sleep(0.02)
"""


@pytest.mark.parametrize("behaviour", ["wakes", "holds"])
def test_stop_names_a_process_it_cannot_defeat(tmp_path: Path, behaviour: str) -> None:
    """A foreign process owns the bus: one that sets the chip up again before every write
    (no SLEEP can hold it), one that holds the bus and never ends. ``stop`` writes the stop,
    then says it cannot confirm it (exit 1), naming the pid; once that process is gone, a
    stop confirms (exit 0)."""
    chip_file = tmp_path / "chip.json"
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run"))
    stop_cmd = [JETBOT_RT, *on_emulator(["stop"], chip_file)]
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(chip_file), behaviour],
                              stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert holder.stdout.readline().strip() == "ready"
        stop = subprocess.run(stop_cmd, capture_output=True, text=True, env=env, timeout=30)
        assert stop.returncode == 1, stop.stdout + stop.stderr
        line = one_line(stop.stderr)
        assert f"pid {holder.pid}" in line and "NOT confirmed off" in line, line
        expected = "set up again" if behaviour == "wakes" else "still owns the bus 3 s later"
        assert expected in line
    finally:
        holder.kill()
        holder.communicate()
    again = subprocess.run(stop_cmd, capture_output=True, text=True, env=env, timeout=30)
    assert again.returncode == 0, again.stderr
    from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

    chip = PCA9685Emulator(0x60, state_file=chip_file)
    assert chip.all_off() and chip.sleeping


@needs_gst
def test_execstoppost_with_an_unreadable_config_finds_the_board_the_runtime_recorded(
        tmp_path: Path) -> None:
    """The runtime drives the board its config names (bus 4, 0x41) and is killed (SIGKILL:
    nothing of its own runs); then its config is replaced by one that cannot be read. The
    ExecStopPost ``stop``, given only that config (no ``--board-emulator``), turns off the
    board the runtime recorded when it took it (not the default bus 1 at 0x60, which would
    report a false failure)."""
    mark = f"fm{uuid.uuid4().hex[:12]}"
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    rt = RuntimeProcess(tmp_path, "real", policy, config=real_config(
        live_camera(mark), motors="i2c_bus = 4\naddress = 0x41") + LOOP)
    from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

    rt.chip_file.unlink()
    rt.chip = PCA9685Emulator(0x41, state_file=rt.chip_file)
    try:
        rt.start()
        rt.wait_ticks(10)
        assert not rt.board_off()
        os.kill(rt.pid, signal.SIGKILL)
        rt.finish(30)
    finally:
        rt.kill()
    assert not rt.board_off(), "nothing turned the board off: the case ExecStopPost is for"
    rt.config.write_bytes(b"[motors]\ni2c_bus = \xff\n")
    stop = subprocess.run([JETBOT_RT, "stop", "--config", str(rt.config)], capture_output=True,
                          text=True, env=rt.env, timeout=30)
    assert stop.returncode == 2, stop.stdout + stop.stderr  # the config is still bad
    line = one_line(stop.stderr)
    assert "not UTF-8" in line and "using the board the runtime recorded in" in line, line
    assert "motor outputs off (I2C bus 4 address 0x41)" in stop.stdout
    assert rt.board_off() and rt.chip.sleeping
    assert_no_gst_left(mark)


# ---- class 3: one owner per bus -----------------------------------------------------------


@needs_gst
# The owner lock is a flock on the bus, not found through the environment: the same
# environment and one with no runtime directory at all (another JETBOT_RT_RUNTIME_DIR ran here
# too until the suite had to fit its 6 minutes).
@pytest.mark.parametrize("env_variant", ["same", "no-runtime-dir"])
def test_a_second_owner_is_refused_whatever_its_environment(tmp_path: Path,
                                                            env_variant: str) -> None:
    rt, mark = start_real(tmp_path)
    try:
        rt.wait_ticks(10)
        if env_variant == "same":
            env = rt.env
        else:
            env = env_without_runtime_dirs(rt, XDG_RUNTIME_DIR=str(tmp_path / "xdg"))
        second = subprocess.run(
            [JETBOT_RT, *on_emulator(["run", "--backend", "real", "--policy", rt.args[4],
                                      "--config", str(rt.config), "--duration", "5"],
                                     rt.chip_file)],
            capture_output=True, text=True, env=env, timeout=60)
        spin = subprocess.run([JETBOT_RT, *on_emulator(["check", "--spin", "--config",
                                                        str(rt.config), "--frames", "2"],
                                                       rt.chip_file)],
                              capture_output=True, text=True, env=env, timeout=60)
        before = rt.tick_count()
        rt.wait_ticks(before + 10)  # the owner drives on
        assert not rt.board_off()
        os.kill(rt.pid, signal.SIGTERM)
        t_off = wait_for(rt.board_off, 10.0)
        result = rt.finish(30)
    finally:
        rt.kill()
    for refused in (second, spin):
        assert refused.returncode == 2, refused.stdout + refused.stderr
        line = one_line(refused.stderr)
        assert f"is driven by pid {rt.pid} (jetbot-rt run --backend real)" in line, line
    assert "spin" not in spin.stdout
    # check --spin would have pulsed 0.3 on channels 1 and 2: the owner's duties never exceed 0.1
    assert max(rt.chip.refresh().peak_duty[:4]) <= 0.1 + 1e-3, rt.chip.peak_duty
    assert result.returncode == 0 and t_off is not None and rt.board_off()
    assert_no_gst_left(mark)


@needs_gst
@pytest.mark.parametrize("attempt", range(2))
def test_two_runtimes_started_at_once_exactly_one_drives(tmp_path: Path, attempt: int) -> None:
    mark = f"fm{uuid.uuid4().hex[:12]}"
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    runs = []
    for name in ("a", "b"):
        root = tmp_path / name
        root.mkdir()
        runs.append(RuntimeProcess(root, "real", policy,
                                   config=real_config(live_camera(mark + name)) + LOOP))
    a, b = runs
    b.chip_file = a.chip_file  # the same board, another runtime directory
    ended = {}
    try:
        for rt in runs:
            rt.start()
        for rt in runs:
            seen = wait_for(lambda rt=rt: rt.process.poll() is not None or rt.tick_count() >= 5,
                            60.0, 0.05)
            assert seen is not None
        for rt in runs:
            if rt.process.poll() is None:
                os.kill(rt.pid, signal.SIGTERM)
            ended[rt.pid] = rt.finish(30)
    finally:
        for rt in runs:
            rt.kill()
    codes = sorted(r.returncode for r in ended.values())
    assert codes == [0, 2], {pid: (r.returncode, r.stderr) for pid, r in ended.items()}
    (driver,) = [pid for pid, r in ended.items() if r.returncode == 0]
    (refused,) = [r for r in ended.values() if r.returncode == 2]
    assert f"is driven by pid {driver}" in one_line(refused.stderr)
    assert a.board_off()
    assert wait_for(lambda: not processes_with(mark), 3.0) is not None


def test_two_simulations_run_side_by_side(tmp_path: Path) -> None:
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    runs = []
    for name in ("one", "two"):
        root = tmp_path / name
        root.mkdir()
        # two worlds at once on a loaded 2-core machine: a slow rate keeps ticks on time
        runs.append(RuntimeProcess(root, "sim", policy, duration=1.0,
                                   config="[loop]\nrate_hz = 10\nwatchdog_timeout = 1.0\n"))
    for rt in runs:
        rt.env["JETBOT_RT_RUNTIME_DIR"] = str(tmp_path / "run")  # one directory for both
        rt.start()
    try:
        results = [rt.finish(90) for rt in runs]
    finally:
        for rt in runs:
            rt.kill()
    for result in results:
        assert result.returncode == 0, result.stdout + result.stderr  # the summary says why
        assert "Traceback" not in result.stderr
        assert result.records[-1]["cmd"] == [0.0, 0.0] and len(result.ticks) >= 5
    assert not list((tmp_path / "run").glob("control-*.sock")), "sockets left behind"


WARM_STOP = """
import sys
from jetbot_rt.cli import main
import jetbot_rt.commands.stop
print("ready", flush=True)
sys.stdin.readline()
sys.exit(main(["stop", "--board-emulator", sys.argv[1]]))
"""


@needs_gst
def test_stop_during_check_spin_ends_the_pulse(tmp_path: Path) -> None:
    """``check --spin`` owns the bus while it pulses: a stop from another environment puts
    the chip to sleep, the pulse's next write fails (its row says why), the wheels stay off,
    and ``stop`` confirms once the pulse has let go of the bus."""
    mark = f"fm{uuid.uuid4().hex[:12]}"
    config = tmp_path / "robot.toml"
    config.write_text(real_config(live_camera(mark)))
    chip_file = tmp_path / "chip.json"
    from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

    chip = PCA9685Emulator(0x60, state_file=chip_file)
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run"))
    # The stop's interpreter is started first and waits for a line: it acts at once, inside
    # the first 0.5 s pulse.
    stop = subprocess.Popen([sys.executable, "-c", WARM_STOP, str(chip_file)],
                            stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(env, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "other")))
    check = subprocess.Popen([JETBOT_RT, *on_emulator(["check", "--spin", "--config",
                                                       str(config), "--frames", "5"], chip_file)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, env=env)
    try:
        assert stop.stdout.readline().strip() == "ready"
        assert wait_for(lambda: not chip.refresh().all_off(), 60.0, 0.005) is not None
        stop_out, stop_err = stop.communicate("\n", timeout=30)
        stopped_off = chip.refresh().all_off()
        out, err = check.communicate(timeout=60)
    finally:
        for proc in (stop, check):
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert stop.returncode == 0, stop_out + stop_err
    assert stopped_off and chip.refresh().all_off() and chip.sleeping
    assert check.returncode == 1, out + err
    assert "Traceback" not in err
    (spin_row,) = [line for line in out.splitlines() if line.startswith("spin")]
    assert "FAIL" in spin_row and "asleep" in spin_row, out
    assert wait_for(lambda: not processes_with(mark), 3.0) is not None
