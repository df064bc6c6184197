import threading
import time

from jetbot_rt.runtime.safety import GuardedDrive, SafeStopLatch, Watchdog
from jetbot_rt.testing.null_robot import NullDrive


def test_latch_first_reason_wins_and_zeroes_the_drive():
    latch = SafeStopLatch()
    drive = NullDrive()
    guarded = GuardedDrive(drive, latch)
    assert guarded.write(0.1, 0.1)
    assert drive.last == (0.1, 0.1)
    assert latch.trip("first")
    assert not latch.trip("second")
    assert latch.reason == "first" and latch.fault
    assert drive.last == (0.0, 0.0)


def test_after_the_latch_only_zero_goes_through_from_any_thread():
    latch = SafeStopLatch()
    drive = NullDrive()
    guarded = GuardedDrive(drive, latch)
    latch.trip("test")
    results = []
    thread = threading.Thread(target=lambda: results.append(guarded.write(0.5, 0.5)))
    thread.start()
    thread.join()
    assert results == [False]
    assert not guarded.write(0.0, 0.1)
    assert guarded.write(0.0, 0.0)
    assert drive.last == (0.0, 0.0)
    assert guarded.refused == 2


def test_stop_errors_are_recorded_not_raised():
    class BrokenDrive(NullDrive):
        def stop(self):
            raise OSError("bus gone")

    latch = SafeStopLatch()
    guarded = GuardedDrive(BrokenDrive(), latch, retry_s=0.05)
    latch.trip("test")
    assert guarded.stop_errors == ["OSError: bus gone"]  # once, however often it was tried
    assert guarded.failed_stops >= 2


class ManualClock:
    """A monotonic clock that moves only when the test moves it."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_watchdog_trips_when_kicks_stop():
    """On a clock the test moves (however late a thread runs on a loaded machine, no kick is
    late): kicked within the timeout it never trips; once the kicks stop and the clock passes
    the timeout it trips, the motors go to zero and the reason says how long, and which key."""
    clock = ManualClock()
    latch = SafeStopLatch()
    drive = NullDrive()
    GuardedDrive(drive, latch)
    drive.last = (0.2, 0.2)
    watchdog = Watchdog(latch, timeout=0.05, clock=clock)
    watchdog.start()
    try:
        for _ in range(10):  # kicked in time: 0.4 s of this clock, no trip
            clock.now += 0.04
            watchdog.kick()
            time.sleep(0.01)  # the watchdog thread looks at its deadline meanwhile
        time.sleep(0.1)  # real time without a kick: only its own clock counts
        assert not latch.tripped and drive.last == (0.2, 0.2)
        clock.now += 0.06
        assert latch.wait(30.0)
        assert latch.fault
        assert latch.reason == ("watchdog: no tick for 0.060 s "
                                "(limit [loop] watchdog_timeout = 0.05 s)")
        assert drive.last == (0.0, 0.0)
    finally:
        watchdog.close()


def test_watchdog_on_the_monotonic_clock_trips_without_kicks():
    latch = SafeStopLatch()
    drive = NullDrive()
    GuardedDrive(drive, latch)
    drive.last = (0.2, 0.2)
    watchdog = Watchdog(latch, timeout=0.05)
    watchdog.start()
    try:
        assert latch.wait(30.0)
        assert latch.reason.startswith("watchdog: no tick for ")
        assert drive.last == (0.0, 0.0)
    finally:
        watchdog.close()


def test_closed_watchdog_does_not_trip():
    latch = SafeStopLatch()
    watchdog = Watchdog(latch, timeout=0.02)
    watchdog.start()
    watchdog.close()
    time.sleep(0.06)
    assert not latch.tripped
