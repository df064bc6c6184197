"""A simulated robot is not a real one: on the sim backend a hiccup of the desktop (the whole
process not scheduled for a while) is no fault, while the robot keeps its 0.1 s watchdog.

Decided: a sim frame's age is simulated time (the world stands still while the process does,
so the image is exactly as old as the world says); the sim's watchdog stays on the wall clock
(a hung policy stops simulated time too, so a watchdog on it would never fire) with a longer
default, ``config.SIM_WATCHDOG_MIN_S`` (1 s), as ``--gui`` lengthens it for slow renders.
The robot's 0.1 s, and the key named in the reason, are checked by the fault matrix
(``test_fault[policy-hangs-real]``): a freeze of the whole process is no fit test for it,
since the loop thread may wake and tick before the watchdog thread looks.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import policy_models
import pytest
from fault_helpers import record_figures
from runner import RuntimeProcess

from jetbot_rt.config.sections import SIM_WATCHDOG_MIN_S, Config, LoopConfig
from jetbot_rt.hal.registry import BackendOptions, make_backend

TICK = 1 / 30
HICCUP_S = 0.4
"""Four times the robot's watchdog timeout, well under the sim's."""


def test_the_sim_waits_a_second_for_a_tick_and_the_robot_a_tenth() -> None:
    loop = LoopConfig()
    assert loop.watchdog_timeout_for(simulated=False) == loop.watchdog_timeout_s == 0.1
    assert loop.watchdog_timeout_for(simulated=True) == SIM_WATCHDOG_MIN_S == 1.0
    slow = LoopConfig(rate_hz=2.0)  # three periods, 1.5 s, are more than either floor
    assert slow.watchdog_timeout_for(simulated=False) == 1.5
    assert slow.watchdog_timeout_for(simulated=True) == 1.5
    chosen = LoopConfig(watchdog_timeout=0.2)  # a value the user set holds on both
    assert chosen.watchdog_timeout_for(simulated=True) == 0.2
    assert chosen.watchdog_timeout_for(simulated=False) == 0.2


def test_a_sim_frame_ages_on_simulated_time_not_on_the_wall_clock() -> None:
    config = Config()
    config.sim.camera_stall_after = 2 * TICK  # the camera freezes after two ticks
    robot = make_backend("sim", config, BackendOptions(frame_size=(32, 32)))
    robot.connect()
    try:
        camera = robot.camera
        camera.start()
        frame = camera.read()
        assert frame is not None
        # however long the wall clock says (a desktop's hiccup), the world has not moved
        assert camera.frame_age(frame, time.monotonic() + 60.0) == 0.0
        ages = []
        for _ in range(6):
            robot.step(TICK)
            frame = camera.read()
            ages.append(camera.frame_age(frame, time.monotonic()))
        # fresh while the camera works; frozen, one period older each tick
        assert ages[:2] == [0.0, 0.0]
        assert ages[2:] == pytest.approx([TICK, 2 * TICK, 3 * TICK, 4 * TICK])
    finally:
        robot.disconnect()


def hiccup(rt: RuntimeProcess) -> None:
    """The whole process stopped for ``HICCUP_S``, then continued: what a loaded desktop does
    to a process now and then (SIGCONT ends no run; only a Ctrl-Z's SIGTSTP is caught)."""
    os.kill(rt.pid, signal.SIGSTOP)
    time.sleep(HICCUP_S)
    os.kill(rt.pid, signal.SIGCONT)


def test_a_hiccup_of_the_whole_process_is_no_fault_on_the_sim(tmp_path: Path) -> None:
    policy = policy_models.constant(tmp_path / "p.onnx", (1.0, 1.0))
    rt = RuntimeProcess(tmp_path, "sim", policy, duration=None)
    try:
        rt.start()
        rt.wait_ticks(10)
        hiccup(rt)
        rt.wait_ticks(rt.tick_count() + 10)  # drives on after it
        os.kill(rt.pid, signal.SIGTERM)
        result = rt.finish(60)
    finally:
        rt.kill()
    assert result.returncode == 0, result.stdout + result.stderr
    (start,) = result.events("start")
    assert start["watchdog_timeout_s"] == SIM_WATCHDOG_MIN_S
    assert result.records[-1]["reason"] == "SIGTERM received"
    gaps = [b["t"] - a["t"] for a, b in zip(result.ticks, result.ticks[1:])]
    assert max(gaps) >= HICCUP_S, "the hiccup did not happen while it drove"
    assert all(r["frame_age_ms"] == 0.0 for r in result.ticks)  # simulated time: none passed
    record_figures("hiccup-sim", exit_code=0, longest_gap_s=round(max(gaps), 4),
                   ticks=len(result.ticks))
