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


def test_watchdog_trips_when_kicks_stop():
    latch = SafeStopLatch()
    drive = NullDrive()
    GuardedDrive(drive, latch)
    drive.last = (0.2, 0.2)
    watchdog = Watchdog(latch, timeout=0.05)
    watchdog.start()
    for _ in range(10):  # kicked in time: no trip
        time.sleep(0.01)
        watchdog.kick()
    assert not latch.tripped
    t_last_kick = time.monotonic()
    assert latch.wait(2.0)
    elapsed = latch.t_trip - t_last_kick
    assert 0.05 <= elapsed < 1.0  # generous upper bound: the machine is shared
    assert latch.reason.startswith("watchdog: no tick for")
    assert drive.last == (0.0, 0.0)
    watchdog.close()


def test_closed_watchdog_does_not_trip():
    latch = SafeStopLatch()
    watchdog = Watchdog(latch, timeout=0.02)
    watchdog.start()
    watchdog.close()
    time.sleep(0.06)
    assert not latch.tripped
