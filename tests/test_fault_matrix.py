"""The fault-injection matrix (docs/SAFETY.md is its written form).

Every fault is injected while the robot drives: ``jetbot-rt run`` in a subprocess, on the sim
backend and on the real backend (a real GStreamer camera, the register-level PCA9685 emulator
as the motor board). Each case checks: the motors end at zero (the sim's last command, the
emulated board's registers) within the case's bound, the telemetry ends with the ``end`` event
naming the cause, the exit code is the documented one, no traceback, no gst-launch left.

Set ``JETBOT_RT_FAULT_FIGURES=<file>`` to append each case's measured times (JSON Lines): the
figures docs/SAFETY.md quotes.
"""

from __future__ import annotations

import os
import shutil
import signal
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import policy_models
import pytest
from fault_helpers import (
    MU,
    SwitchableCamera,
    assert_no_gst_left,
    live_camera,
    needs_gst,
    real_config,
    record_figures,
)
from runner import Result, RuntimeProcess, assert_fixed_rate, processes_with, wait_for

from jetbot_rt.config.sections import SIM_WATCHDOG_MIN_S
from jetbot_rt.runtime.safety import STOP_RETRY_S

PERIOD = 1 / 30
WATCHDOG = 3 * PERIOD  # the default [loop] watchdog_timeout on the robot (the sim's: 1 s)
WATCHDOG_DEFAULT = {"real": WATCHDOG, "sim": SIM_WATCHDOG_MIN_S}
MAX_FRAME_AGE = 0.15  # the default [loop] max_frame_age



# ---- cameras and configs -----------------------------------------------------------------


@dataclass(frozen=True)
class Dark:
    """The lens goes black after ``after_s`` of driving, for ``lasts_s`` (None: for good): the
    sim's ``blackout`` in simulated time; on the real backend a ``SwitchableCamera`` shows a
    black frame once the loop has ticked ``after_s`` worth of periods."""
    after_s: float
    lasts_s: float | None = None

    def sim_config(self) -> str:
        until = 1000.0 if self.lasts_s is None else self.after_s + self.lasts_s
        return f"[sim]\nblackout = [{self.after_s}, {until}]\n"

    def on_real(self, rt: RuntimeProcess, camera: SwitchableCamera) -> None:
        rt.wait_ticks(round(self.after_s / PERIOD))
        camera.show_black()
        if self.lasts_s is not None:
            time.sleep(self.lasts_s)
            camera.show_pattern()


# ---- the cases ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Case:
    name: str
    backends: tuple[str, ...]
    exit_code: int
    reason: str
    """The ``end`` event's reason (and the ``safe_stop`` event's) starts with this."""
    bound_s: float = 0.5
    """Upper bound asserted on: the last command written -> the zero write (the ``safe_stop``
    event, logged once the drive is zeroed)."""
    sim_bound_s: float | None = None
    """``bound_s`` on the sim backend, where it differs (the sim's longer watchdog)."""
    policy: Callable[[Path], Path] = lambda path: policy_models.constant(path, MU)
    sim_config: Callable[[], str] = lambda: ""
    camera: Callable[[str], str] = live_camera
    dark: Dark | None = None
    """A black lens partway (``sim_config`` and ``camera`` then come from it)."""
    loop_config: str = "watchdog_timeout = 1.0\nmax_frame_age = 1.0\n"
    """Patient thresholds by default: a case is about its own fault, and a starved loop on a
    loaded host (CI: two busy cores) tripping the 0.1 s watchdog first is the safety design
    working, not that case's path (seen: policy-raises-sim ended by the watchdog at load 11).
    The watchdog and stale-frame cases keep their defaults."""
    motors: str = "i2c_retries = 3"
    duration: float = 30.0
    inject: Callable[[RuntimeProcess, str], None] | None = None
    """Called with the run and the camera's marker after ``ticks_before`` ticks."""
    ticks_before: int = 15
    check: Callable[[Result, dict, list[dict]], None] | None = None
    board_off_by_runtime: bool = True
    """False where the board cannot be reached: ``jetbot-rt stop`` (ExecStopPost) clears it."""
    timed_off: bool = False
    """Real backend: poll the board from the injection until every output is off."""


def send(sig: int) -> Callable[[RuntimeProcess, str], None]:
    return lambda rt, _mark: os.kill(rt.pid, sig)


def gst_child(rt: RuntimeProcess, mark: str) -> int:
    (pid,) = processes_with(mark)
    return pid


def stall_camera(rt: RuntimeProcess, mark: str) -> None:
    os.kill(gst_child(rt, mark), signal.SIGSTOP)


def kill_camera(rt: RuntimeProcess, mark: str) -> None:
    os.kill(gst_child(rt, mark), signal.SIGKILL)


def stop_command(rt: RuntimeProcess, _mark: str) -> None:
    done = rt.jetbot_rt("stop")
    # "latched its safe stop" when the runtime answers within stop's 0.5 s wait; a sim world
    # starved on a loaded host can answer later (seen at load 11). The run's end reason,
    # asserted by the test, says whether the request reached it.
    assert "Traceback" not in done.stderr, done.stderr
    # on the sim there is no board for its second step to turn off (exit 1: not confirmed)
    assert done.returncode == (0 if rt.chip is not None else 1), done.stderr


def replace_policy(rt: RuntimeProcess, _mark: str) -> None:
    """Atomically replace the model with one that reverses, then overwrite it with garbage."""
    path = Path(rt.args[rt.args.index("--policy") + 1])
    other = policy_models.constant(rt.root / "reverse.onnx", (-1.0, -1.0))
    os.replace(other, path)
    time.sleep(0.5)
    path.write_bytes(b"garbage, not a model")
    time.sleep(0.5)


def i2c_noise(rt: RuntimeProcess, _mark: str) -> None:
    """Three bursts of two failed transfers each: within the retry budget of 3."""
    assert rt.chip is not None
    for _ in range(3):
        rt.chip.update(fail_next=2)
        assert wait_for(lambda: rt.chip.refresh().fail_next == 0, 10.0) is not None
        # fail_next reaches 0 when the second failure happens, before the retry that succeeds:
        # let that retry and a few ticks land, or the next burst would hit the same transfer.
        time.sleep(0.15)
        assert not rt.chip.refresh().all_off(), "still driving after the retried transfers"
        time.sleep(0.2)
    os.kill(rt.pid, signal.SIGTERM)


def i2c_fail(count: int) -> Callable[[RuntimeProcess, str], None]:
    def inject(rt: RuntimeProcess, _mark: str) -> None:
        assert rt.chip is not None
        rt.chip.update(fail_next=count)
    return inject


def board_vanishes(rt: RuntimeProcess, _mark: str) -> None:
    assert rt.chip is not None
    rt.chip.update(absent=True)


def slow_when_dark_policy(path: Path) -> Path:
    """``slow_when_dark`` with its loop sized on this machine, now: about 3 periods per
    inference on a black frame (a fixed count would be faster than a period on an idle PC)."""
    import numpy as np

    from jetbot_rt.runtime.policy import OnnxPolicy

    probe = OnnxPolicy.load(policy_models.slow_when_dark(path, 1000, MU))
    black = np.zeros((policy_models.SIZE, policy_models.SIZE, 3), np.uint8)
    probe.infer(black)
    timings = []
    for _ in range(3):
        t0 = time.perf_counter()
        probe.infer(black)
        timings.append(time.perf_counter() - t0)
    per_iteration = min(timings) / 1000
    return policy_models.slow_when_dark(path, max(1000, round(3 * PERIOD / per_iteration)), MU)


def check_slow_then_recovers(result: Result, end: dict, ticks: list[dict]) -> None:
    slow = [i for i, r in enumerate(ticks) if r["infer_ms"] > PERIOD * 1e3]
    assert slow, "no inference was slower than a period"
    assert end["overruns"] > 0
    after = ticks[slow[-1] + 1:]
    assert len(after) >= 10, "kept driving after the slow stretch"
    assert all(r["cmd"] != [0.0, 0.0] for r in after)
    assert_fixed_rate(ticks, PERIOD)


def check_policy_kept(result: Result, end: dict, ticks: list[dict]) -> None:
    # It drove through both replacements: they start after tick 15 and take 1 s.
    assert ticks[-1]["t"] - ticks[14]["t"] > 1.0
    assert all(r["mu"] == pytest.approx(list(MU)) for r in ticks)


def check_watchdog_names_its_key(result: Result, end: dict, ticks: list[dict]) -> None:
    """The robot keeps its 0.1 s, the sim waits 1 s (a desktop's hiccup is no fault there);
    the reason names the key that changes it."""
    (start,) = result.events("start")
    timeout = WATCHDOG_DEFAULT[start["backend"]]
    assert start["watchdog_timeout_s"] == pytest.approx(timeout)
    assert end["reason"].endswith(f" s (limit [loop] watchdog_timeout = {timeout:.3g} s)"), end
    assert f"stopped      {end['reason']}" in result.stdout


def check_i2c_counted(result: Result, end: dict, ticks: list[dict]) -> None:
    assert end["i2c_retried"] == 6, end
    assert ticks[-1]["i2c_retried"] == 6
    assert "i2c retried  6 transfers" in result.stdout


def check_retries_before_fault(count: int):
    def check(result: Result, end: dict, ticks: list[dict]) -> None:
        assert end["i2c_retried"] == count, end
    return check


def check_stop_errors(result: Result, end: dict, ticks: list[dict]) -> None:
    assert end["stop_errors"], end  # the runtime says its own stop did not reach the board
    assert "stop error" in result.stdout
    # it kept trying for the whole retry window, then said so
    assert end["motors_confirmed_zero"] is False, end
    assert end["motors"].startswith("NOT confirmed zero after "), end
    failed, seconds = end["motors"].split(" failed zero writes in ")
    assert int(failed.rsplit(" ", 1)[1]) >= 2
    assert float(seconds.split(" ")[0]) >= STOP_RETRY_S
    assert f"motors       {end['motors']}" in result.stdout


def check_zero_confirmed_after(failed_zero_writes: int):
    """A burst longer than the retries: the zero write is tried again until the board takes
    it (the tick's write used 4 of the failures: 1 + i2c_retries)."""
    def check(result: Result, end: dict, ticks: list[dict]) -> None:
        assert end["motors_confirmed_zero"] is True, end
        assert end["motors"].startswith(
            f"confirmed zero after {failed_zero_writes} failed zero writes in "), end
        assert f"motors       {end['motors']}" in result.stdout
        assert "stop error" not in result.stdout
    return check


def camera_of_size(width: int, height: int) -> Callable[[str], str]:
    return lambda mark: (f"videotestsrc name={mark} is-live=true ! "
                         f"video/x-raw,format=GRAY8,width={width},height={height}")


DARK = Dark(1.0)  # 30 ticks of driving first
SLOW = Dark(1.0, 0.3)
CASES = [
    # -- policy --
    Case("policy-hangs", ("sim", "real"), 3, "watchdog: no tick for", WATCHDOG + 0.5,
         sim_bound_s=SIM_WATCHDOG_MIN_S + 0.5, policy=policy_models.hang_when_dark,
         dark=DARK, loop_config="max_frame_age = 1.0\n",
         check=check_watchdog_names_its_key),
    Case("policy-slow-then-recovers", ("sim", "real"), 0, "duration", duration=3.5,
         policy=slow_when_dark_policy, dark=SLOW,
         check=check_slow_then_recovers),
    Case("policy-nan", ("sim", "real"), 3, "non-finite action",
         policy=policy_models.nan_when_dark, dark=DARK),
    Case("policy-inf", ("sim",), 3, "non-finite action",  # NaN's path: on both backends
         policy=policy_models.inf_when_dark, dark=DARK),
    Case("policy-raises", ("sim", "real"), 3, "policy inference failed",
         policy=policy_models.raise_when_dark, dark=DARK),
    Case("policy-file-replaced", ("sim",), 0, "duration", duration=2.5, inject=replace_policy,
         check=check_policy_kept),
    # -- camera --
    Case("camera-stalls", ("sim",), 3, "stale frame", MAX_FRAME_AGE + 0.5,
         sim_config=lambda: "[sim]\ncamera_stall_after = 1.0\n",
         loop_config="watchdog_timeout = 1.0\n"),
    Case("camera-stalls-sigstop", ("real",), 3, "stale frame", MAX_FRAME_AGE + 0.5,
         inject=stall_camera, timed_off=True,
         loop_config="watchdog_timeout = 1.0\n"),
    Case("camera-dies-sigkill", ("real",), 3, "stale frame", MAX_FRAME_AGE + 0.5,
         inject=kill_camera, timed_off=True,
         loop_config="watchdog_timeout = 1.0\n"),
    Case("camera-dies-eos", ("real",), 3, "stale frame", MAX_FRAME_AGE + 0.5,
         camera=lambda mark: f"videotestsrc name={mark} is-live=true num-buffers=45",
         loop_config="watchdog_timeout = 1.0\n"),
    Case("camera-other-size-and-format", ("real",), 0, "duration", duration=1.0,
         camera=camera_of_size(640, 120)),
    # -- motors --
    Case("i2c-transient-oserror", ("real",), 0, "SIGTERM received", inject=i2c_noise,
         check=check_i2c_counted),
    Case("i2c-error-burst-beyond-retries", ("real",), 3, "I2C bus 1 address 0x60",
         inject=i2c_fail(4), check=check_retries_before_fault(3), timed_off=True),
    *(Case(f"i2c-burst-of-{count}-failures", ("real",), 3, "I2C bus 1 address 0x60",
           STOP_RETRY_S + 0.5, inject=i2c_fail(count),
           check=check_zero_confirmed_after((count - 4) // 4), timed_off=True)
      for count in (20, 60)),
    Case("i2c-persistent-oserror", ("real",), 3, "I2C bus 1 address 0x60", STOP_RETRY_S + 0.5,
         inject=i2c_fail(10**9), check=check_stop_errors, board_off_by_runtime=False),
    Case("board-vanishes", ("real",), 3, "I2C bus 1 address 0x60", STOP_RETRY_S + 0.5,
         inject=board_vanishes, check=check_stop_errors, board_off_by_runtime=False),
    # -- process --
    # One handler for every ending signal (test_fault_signals.py checks each is caught):
    # SIGINT on both backends, systemd's SIGTERM on the robot, SIGHUP on the sim.
    *(Case(name.lower(), backends, 0, f"{name} received", inject=send(sig), timed_off=True)
      for name, sig, backends in (("SIGINT", signal.SIGINT, ("sim", "real")),
                                  ("SIGTERM", signal.SIGTERM, ("real",)),
                                  ("SIGHUP", signal.SIGHUP, ("sim",)))),
    Case("jetbot-rt-stop", ("sim", "real"), 0, "jetbot-rt stop from pid", inject=stop_command,
         timed_off=True),
    Case("duration", ("sim", "real"), 0, "duration 1 s reached", duration=1.0),
]


def matrix():
    for case in CASES:
        for backend in case.backends:
            marks = [needs_gst] if backend == "real" else []
            yield pytest.param(case, backend, id=f"{case.name}-{backend}", marks=marks)


# ---- the matrix --------------------------------------------------------------------------


@pytest.mark.parametrize(("case", "backend"), list(matrix()))
def test_fault(tmp_path: Path, case: Case, backend: str) -> None:
    mark = f"fm{uuid.uuid4().hex[:12]}"
    policy = case.policy(tmp_path / "policy.onnx")
    loop = f"[loop]\n{case.loop_config}" if case.loop_config else ""
    camera = SwitchableCamera(tmp_path, mark) if case.dark and backend == "real" else None
    if backend == "sim":
        config = case.dark.sim_config() if case.dark else case.sim_config()
    else:
        config = real_config(camera.pipeline if camera else case.camera(mark), case.motors)
    config += loop
    rt = RuntimeProcess(tmp_path, backend, policy, config=config, duration=case.duration)
    inject_to_off = stop_command_s = None
    try:
        rt.start()
        if camera is not None:
            case.dark.on_real(rt, camera)
        if case.inject is not None:
            rt.wait_ticks(case.ticks_before)
            t_inject = time.monotonic()
            case.inject(rt, mark)
            if backend == "real" and case.timed_off:
                t_off = wait_for(rt.board_off, 15.0)
                assert t_off is not None, "the board was not turned off"
                inject_to_off = t_off - t_inject
        result = rt.finish(90)
    finally:
        rt.kill()

    assert result.returncode == case.exit_code, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    records = result.records
    end = records[-1]
    assert end["event"] == "end", records[-3:]
    assert end["reason"].startswith(case.reason), end
    assert end["exit_code"] == case.exit_code and end["cmd"] == [0.0, 0.0]
    (stop,) = result.events("safe_stop")
    assert stop["reason"] == end["reason"] and stop["cmd"] == [0.0, 0.0]
    assert stop["fault"] == (case.exit_code == 3)
    ticks = result.ticks
    assert sum(r["cmd"] != [0.0, 0.0] for r in ticks) >= 10, "it was driving before the fault"
    # A tick's record is written after its world step, so it can follow the safe_stop event in
    # the file; its write to the drive must precede the zero write all the same.
    writes = [r["t"] + (r["infer_ms"] + r["write_ms"]) / 1e3 for r in ticks]
    assert max(writes) <= stop["t"] + 1e-3, "a command written after the safe stop"
    exposure = stop["t"] - max(writes)
    bound = case.sim_bound_s if backend == "sim" and case.sim_bound_s else case.bound_s
    assert exposure <= bound, f"{exposure:.3f} s from the last command to the zero write"
    newest_frame = max(r["t"] - r["frame_age_ms"] / 1e3 for r in ticks)

    if backend == "real":
        assert_no_gst_left(mark)
        if not case.board_off_by_runtime:
            assert not rt.board_off(), "an unreachable board cannot have been turned off"
            rt.chip.update(fail_next=0, absent=False)  # the bus comes back; ExecStopPost:
            t0 = time.monotonic()
            done = rt.jetbot_rt("stop")
            stop_command_s = time.monotonic() - t0
            assert done.returncode == 0, done.stderr
        assert rt.board_off(), rt.chip.duties()
    if case.check is not None:
        case.check(result, end, ticks)
    record_figures(f"{case.name}-{backend}", exit_code=result.returncode,
                   last_write_to_zero_s=round(exposure, 4),
                   last_frame_to_zero_s=round(stop["t"] - newest_frame, 4),
                   inject_to_board_off_s=inject_to_off and round(inject_to_off, 4),
                   stop_command_s=stop_command_s and round(stop_command_s, 4),
                   ticks=len(ticks), overruns=end.get("overruns"))


# ---- the process dies: only ExecStopPost is left -----------------------------------------


@needs_gst
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGABRT], ids=["SIGKILL", "SIGABRT"])
def test_killed_runtime_then_jetbot_rt_stop(tmp_path: Path, sig: int) -> None:
    """SIGKILL (systemd's last resort) and SIGABRT (the unit's FinalKillSignal) end the process
    before any handler of ours runs: the board keeps its duties until ``jetbot-rt stop``,
    which systemd runs as ExecStopPost, turns every output off. The camera child dies with
    its parent (PR_SET_PDEATHSIG)."""
    mark = f"fm{uuid.uuid4().hex[:12]}"
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    rt = RuntimeProcess(tmp_path, "real", policy, config=real_config(live_camera(mark)))
    try:
        rt.start()
        rt.wait_ticks(15)
        assert not rt.board_off()
        os.kill(rt.pid, sig)
        result = rt.finish(30)
    finally:
        rt.kill()
    assert result.returncode == -sig
    assert_no_gst_left(mark)
    assert not result.events("end"), "nothing of ours ran"
    assert not rt.board_off(), "nothing turned the board off: the case ExecStopPost is for"
    if sig == signal.SIGABRT:  # faulthandler leaves every thread's stack for the journal
        assert "Fatal Python error: Aborted" in result.stderr
    t0 = time.monotonic()
    done = rt.jetbot_rt("stop")
    elapsed = time.monotonic() - t0
    assert done.returncode == 0, done.stderr
    assert "motor outputs off" in done.stdout
    assert "latched" not in done.stdout  # the stale control socket did not answer
    assert rt.board_off(), rt.chip.duties()
    record_figures(f"{signal.Signals(sig).name}-then-stop-real", exit_code=result.returncode,
                   stop_command_s=round(elapsed, 4))


# ---- telemetry that can no longer be written ---------------------------------------------


def summary_value(stdout: str, label: str) -> str:
    (line,) = [ln for ln in stdout.splitlines() if ln.strip().startswith(label)]
    return line.strip()[len(label):].strip()


@needs_gst
@pytest.mark.parametrize("where", ["dev-full", "directory-removed"])
def test_unwritable_telemetry_keeps_driving_and_counts_lost_records(tmp_path: Path,
                                                                    where: str) -> None:
    """Decided: telemetry is for people, the safety chain does not depend on it. The robot
    keeps driving; one line on stderr; the summary counts the records lost."""
    mark = f"fm{uuid.uuid4().hex[:12]}"
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    directory = tmp_path / "telemetry"
    directory.mkdir()
    path = Path("/dev/full") if where == "dev-full" else directory / "t.jsonl"
    rt = RuntimeProcess(tmp_path, "real", policy, config=real_config(live_camera(mark)),
                        telemetry=path)
    try:
        rt.start()
        if where == "dev-full":
            assert wait_for(lambda: not rt.board_off(), 60, interval=0.05) is not None
        else:
            rt.wait_ticks(15)
            shutil.rmtree(directory)
        time.sleep(1.0)  # 30 ticks at 30 Hz: at least 20 on a loaded host
        assert rt.process.poll() is None and not rt.board_off(), "still driving"
        t_signal = time.monotonic()
        os.kill(rt.pid, signal.SIGTERM)
        t_off = wait_for(rt.board_off, 15)
        result = rt.finish(30)
    finally:
        rt.kill()
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Traceback" not in result.stderr
    expected = "No space left on device" if where == "dev-full" else "file removed while running"
    (line,) = [ln for ln in result.stderr.splitlines() if "telemetry" in ln]
    assert expected in line and "still driving" in line
    lost = int(summary_value(result.stdout, "telemetry").split()[0])
    assert lost >= 20, result.stdout  # two thirds of a second of ticks, and the end event
    assert int(summary_value(result.stdout, "ticks")) >= 20
    assert summary_value(result.stdout, "stopped") == "SIGTERM received"
    assert t_off is not None and rt.board_off()
    assert_no_gst_left(mark)
    record_figures(f"telemetry-{where}-real", exit_code=0, records_lost=lost,
                   inject_to_board_off_s=round(t_off - t_signal, 4))
