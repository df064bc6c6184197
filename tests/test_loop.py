import json
import threading
import time

import numpy as np

from jetbot_rt.errors import Fault
from jetbot_rt.recording.telemetry import Telemetry
from jetbot_rt.runtime.actions import ActionPipeline
from jetbot_rt.runtime.loop import ControlLoop, Schedule, StopChain
from jetbot_rt.runtime.safety import GuardedDrive, SafeStopLatch, Watchdog
from jetbot_rt.testing.null_robot import NullCamera, NullDrive, PartsRobot


class ScriptedPolicy:
    """Returns mu from a list; sleeps on the ticks named in ``slow``."""

    def __init__(self, mus, slow=None):
        self.mus = mus
        self.slow = slow or {}
        self.calls = 0

    def infer(self, image):
        self.calls += 1
        time.sleep(self.slow.get(self.calls, 0.0))
        return np.array(self.mus[min(self.calls, len(self.mus)) - 1])


def make_loop(policy, period=0.02, camera=None, timeout=None, telemetry=None):
    latch = SafeStopLatch()
    drive = NullDrive()
    guarded = GuardedDrive(drive, latch)
    watchdog = Watchdog(latch, timeout) if timeout else None
    loop = ControlLoop(
        robot=PartsRobot(camera or NullCamera(), drive), policy=policy, actions=ActionPipeline(),
        safety=StopChain(latch, guarded, watchdog), schedule=Schedule(period, max_frame_age=0.1),
        observers=[telemetry.observe] if telemetry is not None else [],
    )
    return loop, latch, drive, watchdog


def test_duration_end_is_not_a_fault_and_rate_holds():
    loop, latch, drive, _ = make_loop(ScriptedPolicy([[1.0, 0.5]]))
    loop.run(duration=0.5)
    assert latch.tripped and not latch.fault
    assert "duration" in latch.reason
    assert 20 <= loop.stats.ticks <= 26  # 25 deadlines in 0.5 s at 50 Hz
    assert drive.last == (0.0, 0.0)


def test_overrun_skips_missed_ticks_and_never_bursts():
    # tick 5 takes 3.5 periods: ticks 6..8 deadlines pass; the loop skips them, counts them
    period = 0.02
    loop, _, _, _ = make_loop(ScriptedPolicy([[0.1, 0.1]], slow={5: 3.5 * period}), period)
    starts = []
    original = loop._tick

    def recording_tick(deadline, now):
        starts.append(now)
        original(deadline, now)

    loop._tick = recording_tick
    loop.run(duration=0.4)
    assert loop.stats.overruns >= 3  # a late wake-up under load may skip one more
    gaps = np.diff(starts)
    # never two ticks closer than most of a period: no burst after the slow tick
    assert gaps.min() > 0.5 * period
    assert gaps.max() >= 3.5 * period


def test_non_finite_action_latches_fault(tmp_path):
    path = tmp_path / "t.jsonl"
    telemetry = Telemetry(path)
    loop, latch, drive, _ = make_loop(
        ScriptedPolicy([[1.0, 1.0], [1.0, 1.0], [float("nan"), 0.0]]), telemetry=telemetry
    )
    loop.run(duration=2.0)
    telemetry.close()
    assert latch.fault and "non-finite" in latch.reason
    assert loop.stats.ticks == 2
    assert drive.last == (0.0, 0.0)


def test_stale_frame_latches_fault():
    class FrozenCamera(NullCamera):
        def __init__(self):
            super().__init__()
            self.frame = super().read()

        def read(self):
            return self.frame

    loop, latch, _, _ = make_loop(ScriptedPolicy([[1.0, 1.0]]), camera=FrozenCamera())
    loop.run(duration=2.0)
    assert latch.fault and latch.reason.startswith("stale frame")


def test_exception_in_tick_latches_fault():
    class Exploding:
        def infer(self, image):
            raise RuntimeError("boom")

    loop, latch, _, _ = make_loop(Exploding())
    loop.run(duration=1.0)
    assert latch.fault and latch.reason == "exception in tick: RuntimeError: boom"


class StoppedFromElsewhere(Fault):
    STOP_REQUEST_GRACE_S = 0.5


class RaisesOnTick:
    def __init__(self, fault: Fault, on_raise=None):
        self.fault, self.on_raise = fault, on_raise

    def infer(self, image):
        if self.on_raise is not None:
            self.on_raise()
        raise self.fault


def test_a_fault_with_a_grace_ends_in_order_when_the_stop_request_arrives_within_it():
    loop, latch, _, _ = make_loop(None)
    request = threading.Timer(0.05, latch.trip, ("jetbot-rt stop from pid 1",),
                              {"fault": False})
    loop.policy = RaisesOnTick(StoppedFromElsewhere("board asleep"), request.start)
    loop.run(duration=2.0)
    assert not latch.fault and latch.reason == "jetbot-rt stop from pid 1"


def test_a_fault_with_a_grace_is_a_fault_when_no_stop_request_arrives():
    loop, latch, _, _ = make_loop(RaisesOnTick(StoppedFromElsewhere("board asleep")))
    loop.run(duration=2.0)
    assert latch.fault and latch.reason == "board asleep"
    assert latch.t_trip - loop.stats.t_start >= 0.5


def test_a_fault_without_a_grace_trips_at_once_even_if_a_stop_request_follows():
    loop, latch, _, _ = make_loop(None)
    request = threading.Timer(0.05, latch.trip, ("jetbot-rt stop from pid 1",),
                              {"fault": False})
    loop.policy = RaisesOnTick(Fault("plain fault"), request.start)
    loop.run(duration=2.0)
    request.join()
    assert latch.fault and latch.reason == "plain fault"


def test_watchdog_stops_a_hung_tick():
    loop, latch, drive, watchdog = make_loop(
        ScriptedPolicy([[1.0, 1.0]], slow={4: 0.5}), period=0.02, timeout=0.06
    )
    watchdog.start()
    loop.run(duration=2.0)
    watchdog.close()
    assert latch.fault and latch.reason.startswith("watchdog")
    assert drive.last == (0.0, 0.0)
    assert loop.stats.ticks == 3


def test_observers_see_each_tick_as_telemetry_records_it(tmp_path):
    path = tmp_path / "t.jsonl"
    telemetry = Telemetry(path)
    policy = ScriptedPolicy([[0.5, -0.25], [1.0, 0.0]])
    loop, _, _, _ = make_loop(policy, telemetry=telemetry)
    seen = []
    loop.observers.append(seen.append)
    loop.run(duration=0.2)
    telemetry.close()
    records = [json.loads(line) for line in path.read_text().splitlines()]
    assert len(seen) == loop.stats.ticks == len(records) >= 2
    for result, record in zip(seen, records):
        assert result.record(telemetry.t0) == record
        assert result.image.shape == (224, 224, 3) and result.image.dtype == np.uint8
    assert seen[0].mu == [0.5, -0.25] and seen[0].cmd == (0.05, -0.025)


class CameraWithItsOwnClock(NullCamera):
    """Frames that arrive fresh on the wall clock, aged by a clock of the camera's own (the
    sim's simulated time): the camera says how old a frame is, not the wall clock."""

    def __init__(self, ages):
        super().__init__()
        self.ages = ages
        self.asked = []

    def frame_age(self, frame, now):
        self.asked.append(now)
        return self.ages[min(len(self.asked), len(self.ages)) - 1]


def test_the_camera_says_how_old_a_frame_is():
    camera = CameraWithItsOwnClock([0.0, 0.05, 0.1, 0.25])
    loop, latch, drive, _ = make_loop(ScriptedPolicy([[1.0, 1.0]]), camera=camera)
    loop.run(duration=5.0)
    assert latch.fault
    # the 4th frame, 0.25 s old by the camera's clock, is the first over max_frame_age 0.1 s
    assert loop.stats.ticks == 3 and len(camera.asked) == 4
    assert latch.reason == "stale frame: 250 ms old (limit [loop] max_frame_age = 0.1 s)"
    assert drive.last == (0.0, 0.0)


def test_a_frame_old_on_the_wall_clock_is_fresh_if_its_camera_says_so():
    class OldOnTheWallClock(CameraWithItsOwnClock):
        def read(self):
            frame = super().read()
            return type(frame)(frame.image, frame.t_capture - 10.0, frame.index)

    loop, latch, _, _ = make_loop(ScriptedPolicy([[1.0, 1.0]]), camera=OldOnTheWallClock([0.0]))
    loop.run(duration=0.2)
    assert not latch.fault, latch.reason
    assert loop.stats.ticks >= 2
