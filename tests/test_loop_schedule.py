"""The control loop's schedule in simulated time: exact deadlines, overrun counts, no burst.

The loop runs unchanged on a clock the test owns: the policy's inference advances it by the
tick's scripted duration, and waiting on the latch advances it by the wait (plus a scripted
late wake-up). So every tick start is known exactly, whatever the load on the machine.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from jetbot_rt.hal.base import Camera, Frame
from jetbot_rt.hal.i2c import I2CBus
from jetbot_rt.hal.motors import WaveshareDrive
from jetbot_rt.recording.telemetry import Telemetry
from jetbot_rt.runtime.actions import ActionPipeline
from jetbot_rt.runtime.loop import ControlLoop, Schedule, StopChain, TickObserver, TickResult
from jetbot_rt.runtime.safety import GuardedDrive, SafeStopLatch
from jetbot_rt.testing.null_robot import PartsRobot
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

PERIOD = 0.25  # a power of two: every sum of periods below is exact in binary floating point


class SimulatedClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class SimulatedTimeLatch(SafeStopLatch):
    """Waiting advances the simulated clock instead of sleeping; ``late`` maps a wait's
    index (1-based: the wait after tick N) to how much later than asked the loop wakes up."""

    def __init__(self, clock: SimulatedClock, late: dict[int, float] | None = None) -> None:
        super().__init__()
        self.clock = clock
        self.late = late or {}
        self.waits = 0

    def wait(self, timeout: float | None = None) -> bool:
        self.waits += 1
        assert timeout is not None and timeout >= 0.0
        self.clock.now += timeout + self.late.get(self.waits, 0.0)
        return self.tripped


class FreshCamera(Camera):
    """Always a frame captured ``age`` ago in simulated time."""

    def __init__(self, clock: SimulatedClock, age: float = 0.0) -> None:
        self.clock = clock
        self.age = age
        self.index = 0
        self.image = np.zeros((4, 4, 3), np.uint8)

    def start(self) -> None:
        pass

    def read(self) -> Frame:
        self.index += 1
        return Frame(self.image, self.clock() - self.age, self.index)

    def stop(self) -> None:
        pass


class TimedPolicy:
    """Inference takes ``durations[n]`` of simulated time on its n-th call (default 0)."""

    def __init__(self, clock: SimulatedClock, durations: dict[int, float]) -> None:
        self.clock = clock
        self.durations = durations
        self.calls = 0
        self.starts: list[float] = []

    def infer(self, image: np.ndarray) -> np.ndarray:
        self.calls += 1
        self.starts.append(self.clock())
        self.clock.now += self.durations.get(self.calls, 0.0)
        return np.array([0.5, 0.5])


class TimedDrive(WaveshareDrive):
    """The Waveshare driver on the emulated chip; each write takes ``write_s`` of simulated
    time (the I2C transfer)."""

    def __init__(self, chip: PCA9685Emulator, clock: SimulatedClock, write_s: float) -> None:
        super().__init__(I2CBus(chip, 1), 0x60, 1600.0)
        self.clock = clock
        self.write_s = write_s

    def write(self, left: float, right: float) -> None:
        super().write(left, right)
        self.clock.now += self.write_s


class SteppingRobot(PartsRobot):
    """A simulated robot whose step (the sim's world step, outside the timed part of the
    tick) takes ``step_s`` of simulated time."""

    simulated = True

    def __init__(self, camera: Camera, drive: TimedDrive, clock: SimulatedClock,
                 step_s: float) -> None:
        super().__init__(camera, drive)
        self.clock = clock
        self.step_s = step_s

    def step(self, dt: float) -> None:
        self.clock.now += self.step_s


def run_loop(durations: dict[int, float], duration: float, late: dict[int, float] | None = None,
             telemetry: Telemetry | None = None, frame_age: float = 0.0, write_s: float = 0.0,
             advance_s: float | None = None, observers: list[TickObserver] | None = None,
             ) -> tuple[ControlLoop, TimedPolicy, SimulatedTimeLatch, PCA9685Emulator]:
    clock = SimulatedClock()
    latch = SimulatedTimeLatch(clock, late)
    chip = PCA9685Emulator(0x60)
    timed_drive = TimedDrive(chip, clock, write_s)
    drive = GuardedDrive(timed_drive, latch)
    policy = TimedPolicy(clock, durations)
    robot = (PartsRobot(FreshCamera(clock, frame_age), timed_drive) if advance_s is None
             else SteppingRobot(FreshCamera(clock, frame_age), timed_drive, clock, advance_s))
    if telemetry is not None:
        telemetry.t0 = 0.0  # records' t on the simulated clock
    loop = ControlLoop(
        robot=robot, policy=policy, actions=ActionPipeline(),
        safety=StopChain(latch, drive),
        schedule=Schedule(PERIOD, max_frame_age=1000.0, clock=clock),
        observers=([telemetry.observe] if telemetry is not None else []) + (observers or []),
    )
    loop.run(duration=duration)
    return loop, policy, latch, chip


def periods(times: list[float]) -> list[float]:
    return [t / PERIOD for t in times]


class TestOverrunShorterThanAPeriod:
    """A tick that ends less than one period past the next deadline: that deadline is missed
    (counted), and the next tick runs on its own deadline, not late on the missed one."""

    def test_half_a_period_over_skips_and_counts_one(self) -> None:
        loop, policy, _, _ = run_loop({3: 1.5 * PERIOD}, duration=8 * PERIOD)
        assert periods(policy.starts) == [0, 1, 2, 4, 5, 6, 7]
        assert loop.stats.overruns == 1

    def test_a_sliver_over_still_counts(self) -> None:
        loop, policy, _, _ = run_loop({2: 1.0625 * PERIOD}, duration=6 * PERIOD)
        assert periods(policy.starts) == [0, 1, 3, 4, 5]
        assert loop.stats.overruns == 1

    def test_ending_exactly_on_the_next_deadline_is_on_time(self) -> None:
        loop, policy, _, _ = run_loop({2: 1.0 * PERIOD}, duration=5 * PERIOD)
        assert periods(policy.starts) == [0, 1, 2, 3, 4]
        assert loop.stats.overruns == 0

    @pytest.mark.parametrize(("slow", "starts", "overruns"), [
        (2.5, [0, 1, 2, 5, 6], 2),
        (3.5, [0, 1, 2, 6], 3),
        (3.75, [0, 1, 2, 6], 3),
    ])
    def test_longer_overruns_skip_every_missed_deadline(self, slow: float, starts: list[float],
                                                        overruns: int) -> None:
        loop, policy, _, _ = run_loop({3: slow * PERIOD}, duration=7 * PERIOD)
        assert periods(policy.starts) == starts
        assert loop.stats.overruns == overruns


class TestLateWakeUp:
    """A tick that starts over half a period late does not get a successor a moment later."""

    def test_more_than_half_a_period_late_skips_the_next_deadline(self) -> None:
        loop, policy, _, _ = run_loop({}, duration=6 * PERIOD, late={2: 0.75 * PERIOD})
        assert periods(policy.starts) == [0, 1, 2.75, 4, 5]
        assert loop.stats.overruns == 1

    def test_less_than_half_a_period_late_keeps_the_next_deadline(self) -> None:
        loop, policy, _, _ = run_loop({}, duration=5 * PERIOD, late={2: 0.25 * PERIOD})
        assert periods(policy.starts) == [0, 1, 2.25, 3, 4]
        assert loop.stats.overruns == 0


class TestDurationAndRecords:
    def test_duration_ends_on_its_deadline_without_a_fault(self, tmp_path) -> None:
        telemetry = Telemetry(tmp_path / "t.jsonl")
        loop, policy, latch, chip = run_loop({3: 1.5 * PERIOD}, duration=6 * PERIOD,
                                             telemetry=telemetry)
        telemetry.close()
        assert periods(policy.starts) == [0, 1, 2, 4, 5]
        assert loop.stats.ticks == 5
        assert latch.tripped and not latch.fault
        assert latch.reason == "duration 1.5 s reached"
        assert chip.all_off()
        assert loop.stats.elapsed == 6 * PERIOD
        assert loop.stats.achieved_hz == pytest.approx(5 / (6 * PERIOD))
        records = [json.loads(line) for line in (tmp_path / "t.jsonl").read_text().splitlines()]
        assert [r["tick"] for r in records] == [1, 2, 3, 4, 5]
        assert [r["overruns"] for r in records] == [0, 0, 0, 1, 1]
        assert [r["late_ms"] for r in records] == [0.0] * 5  # each on its own deadline
        assert [r["infer_ms"] for r in records] == [0.0, 0.0, 375.0, 0.0, 0.0]
        assert all(r["cmd"] == [0.05, 0.05] and r["mu"] == [0.5, 0.5] for r in records)
        assert "advance_ms" not in records[0]

    def test_every_timing_field_of_the_records(self, tmp_path) -> None:
        telemetry = Telemetry(tmp_path / "t.jsonl")
        # inference 31.25 ms on tick 2, writes 15.625 ms, sim step 62.5 ms, frames 125 ms old,
        # tick 3 wakes 0.25 period late
        loop, policy, _, _ = run_loop({2: PERIOD / 8}, duration=4 * PERIOD, telemetry=telemetry,
                                      late={2: PERIOD / 4}, frame_age=PERIOD / 2,
                                      write_s=PERIOD / 16, advance_s=PERIOD / 4)
        telemetry.close()
        assert periods(policy.starts) == [0, 1, 2.25, 3]
        records = [json.loads(line) for line in (tmp_path / "t.jsonl").read_text().splitlines()]
        assert [r["t"] for r in records] == [0.0, 0.25, 0.5625, 0.75]
        assert [r["late_ms"] for r in records] == [0.0, 0.0, 62.5, 0.0]
        assert [r["frame_age_ms"] for r in records] == [125.0] * 4
        assert [r["infer_ms"] for r in records] == [0.0, 31.25, 0.0, 0.0]
        assert [r["write_ms"] for r in records] == [15.625] * 4
        assert [r["advance_ms"] for r in records] == [62.5] * 4
        # the tick is read -> update -> write; the sim step is timed apart
        assert [r["tick_ms"] for r in records] == [15.625, 46.875, 15.625, 15.625]
        assert [r["overruns"] for r in records] == [0] * 4
        assert loop.stats.tick_ms.max == 46.875
        assert loop.stats.infer_ms.max == 31.25


class TestStaleFrameReason:
    def test_the_reason_names_the_age_and_the_limit(self) -> None:
        clock = SimulatedClock()
        latch = SimulatedTimeLatch(clock)
        chip = PCA9685Emulator(0x60)
        timed_drive = TimedDrive(chip, clock, 0.0)
        drive = GuardedDrive(timed_drive, latch)
        loop = ControlLoop(
            robot=PartsRobot(FreshCamera(clock, age=0.375), timed_drive),
            policy=TimedPolicy(clock, {}), actions=ActionPipeline(),
            safety=StopChain(latch, drive),
            schedule=Schedule(PERIOD, max_frame_age=0.25, clock=clock),
        )
        loop.run(duration=4 * PERIOD)
        assert latch.fault
        assert latch.reason == "stale frame: 375 ms old (limit [loop] max_frame_age = 0.25 s)"
        assert loop.stats.ticks == 0 and chip.all_off()


class TestWhatObserversGet:
    def test_a_ticks_end_is_when_its_write_returned_not_after_the_sim_step(self) -> None:
        results: list[TickResult] = []
        run_loop({2: PERIOD / 8}, duration=3 * PERIOD, write_s=PERIOD / 16,
                 advance_s=PERIOD / 4, observers=[results.append])
        assert [(r.t_start, r.t_end) for r in results] == [
            (0.0, 0.015625), (0.25, 0.296875), (0.5, 0.515625)]

    def test_the_record_of_a_tick_rounds_durations_to_the_microsecond_and_keeps_the_backends_fields(
            self) -> None:
        result = TickResult(
            tick=3, t_start=10.5, deadline=10.5, image=np.zeros((2, 2, 3), np.uint8),
            frame_index=7, frame_age_ms=1.23456, mu=[0.5, -0.5], cmd=(0.05, -0.05),
            infer_ms=2.00049, tick_ms=3.00051, write_ms=0.99949, advance_ms=4.44444, overruns=1,
            extra={"pose": [1.0, 2.0, 0.5], "sim_time": 0.75})
        assert result.record(t0=10.0) == {
            "t": 0.5, "tick": 3, "state": "driving", "mu": [0.5, -0.5], "cmd": [0.05, -0.05],
            "frame_age_ms": 1.235, "infer_ms": 2.0, "tick_ms": 3.001, "overruns": 1,
            "late_ms": 0.0, "write_ms": 0.999, "advance_ms": 4.444,
            "pose": [1.0, 2.0, 0.5], "sim_time": 0.75}

    @pytest.mark.parametrize("name", ["result", "schedule", "chain"])
    def test_what_the_loop_hands_out_cannot_be_changed_by_its_receiver(self, name: str) -> None:
        import dataclasses

        results: list[TickResult] = []
        loop, _, _, _ = run_loop({}, duration=PERIOD, observers=[results.append])
        target, field = {"result": (results[0], "cmd"), "schedule": (loop.schedule, "period"),
                         "chain": (loop.safety, "watchdog")}[name]
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(target, field, None)
