"""The latch, the guarded drive and the watchdog against the bugs that slip past end-to-end
runs: a write racing the latch's callbacks, a stop stuck behind a hung write, the watchdog's
deadline arithmetic. The drive is the Waveshare driver on the register-level PCA9685 emulator;
the watchdog runs its real thread on a clock the test moves by hand.
"""

from __future__ import annotations

import threading

import pytest

from jetbot_rt.hal.i2c import I2CBus
from jetbot_rt.hal.motors import WaveshareDrive
from jetbot_rt.safety import GuardedDrive, SafeStopLatch, Watchdog
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

LIVENESS_S = 10.0
"""How long a test waits for something that must happen (never asserted as a duration)."""


def emulated_drive() -> tuple[PCA9685Emulator, WaveshareDrive]:
    chip = PCA9685Emulator(0x60)
    return chip, WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0)


class TestLatchIsSetBeforeItsCallbacksRun:
    """A write from another thread while the trip's callbacks still run (the runtime's second
    callback logs telemetry, which may be slow) must be refused: the flag comes first."""

    def test_a_write_during_a_slow_callback_is_refused(self) -> None:
        chip, drive = emulated_drive()
        latch = SafeStopLatch()
        guarded = GuardedDrive(drive, latch)
        assert guarded.write(0.5, 0.5)
        assert not chip.all_off()
        results: list[bool] = []

        def slow_callback(_reason: str) -> None:
            # the loop thread's tick lands while this callback runs
            writer = threading.Thread(target=lambda: results.append(guarded.write(0.7, 0.7)))
            writer.start()
            writer.join(LIVENESS_S)

        latch.on_trip(slow_callback)
        assert latch.trip("test")
        assert results == [False]
        assert guarded.refused == 1
        assert chip.all_off(), chip.duties()

    def test_tripped_is_visible_to_every_callback(self) -> None:
        latch = SafeStopLatch()
        seen: list[tuple[bool, str | None]] = []
        latch.on_trip(lambda reason: seen.append((latch.tripped, latch.reason)))
        latch.on_trip(lambda reason: seen.append((latch.tripped, reason)))
        assert latch.trip("why", fault=False)
        assert seen == [(True, "why"), (True, "why")]
        assert not latch.fault

    def test_only_the_first_trip_runs_the_callbacks(self) -> None:
        latch = SafeStopLatch()
        calls: list[str] = []
        latch.on_trip(calls.append)
        trippers = [threading.Thread(target=latch.trip, args=(f"r{i}",)) for i in range(8)]
        for thread in trippers:
            thread.start()
        for thread in trippers:
            thread.join(LIVENESS_S)
        assert len(calls) == 1
        assert calls == [latch.reason]
        assert latch.t_trip is not None


class HangingWriteDrive(WaveshareDrive):
    """The Waveshare driver whose next write blocks in the "driver" until released, as an
    I2C transfer stuck in the kernel would; its stop goes to the chip as usual."""

    def __init__(self, bus: I2CBus) -> None:
        super().__init__(bus, 0x60, 1600.0)
        self.hang = threading.Event()
        self.release = threading.Event()
        self.in_write = threading.Event()

    def write(self, left: float, right: float) -> None:
        if self.hang.is_set():
            self.in_write.set()
            self.release.wait(LIVENESS_S)
            return
        super().write(left, right)


class TestStopDoesNotWaitForAHungWrite:
    def test_the_stop_goes_out_while_a_write_hangs(self) -> None:
        chip = PCA9685Emulator(0x60)
        drive = HangingWriteDrive(I2CBus(chip, 1))
        latch = SafeStopLatch()
        guarded = GuardedDrive(drive, latch)
        assert guarded.write(0.5, -0.5)
        drive.hang.set()
        writer = threading.Thread(target=guarded.write, args=(0.6, 0.6), daemon=True)
        writer.start()
        try:
            assert drive.in_write.wait(LIVENESS_S)
            tripper = threading.Thread(target=latch.trip, args=("test",), daemon=True)
            tripper.start()
            tripper.join(LIVENESS_S)
            # the stop returned while the write still hangs, and it reached the board
            assert not tripper.is_alive(), "the stop waited for the hung write"
            assert writer.is_alive()
            assert chip.all_off(), chip.duties()
            assert guarded.stop_errors == [
                "a drive write in flight did not return; stopped anyway"
            ]
        finally:
            drive.release.set()
            writer.join(LIVENESS_S)
        # the hung write, once it returns, cannot have started anything
        assert chip.all_off()
        assert not guarded.write(0.3, 0.3)

    def test_a_stop_without_a_write_in_flight_reports_nothing(self) -> None:
        chip, drive = emulated_drive()
        guarded = GuardedDrive(drive, SafeStopLatch())
        guarded.write(0.4, 0.4)
        guarded.stop()
        guarded.stop()
        assert chip.all_off()
        assert guarded.stop_errors == []
        assert guarded.write(0.2, 0.0), "a stop outside the latch leaves the drive usable"
        assert not chip.all_off()


class ManualClock:
    """``time.monotonic`` for the watchdog, moved only by the test."""

    def __init__(self, start: float = 100.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now


TIMEOUT = 0.25
"""In the manual clock's seconds. Also the longest the watchdog thread sleeps in real time
before it looks at the clock again, so the tests do not wait long for it to notice."""


def settle(watchdog: Watchdog) -> None:
    """Give the watchdog's thread a chance to look at the clock: a kick wakes it (and
    re-reads the clock). Only used where the test then expects *no* trip."""
    threading.Event().wait(2 * TIMEOUT)


class TestWatchdogOnAManualClock:
    """The watchdog's deadline from its own clock: trips exactly when ``timeout`` has passed
    since the last kick on that clock, never before, names the silence, and not after close."""

    def make(self) -> tuple[ManualClock, SafeStopLatch, Watchdog, PCA9685Emulator]:
        clock = ManualClock()
        latch = SafeStopLatch()
        chip, drive = emulated_drive()
        guarded = GuardedDrive(drive, latch)
        guarded.write(0.5, 0.5)
        return clock, latch, Watchdog(latch, TIMEOUT, clock=clock), chip

    def test_kicks_within_the_timeout_never_trip(self) -> None:
        clock, latch, watchdog, chip = self.make()
        watchdog.start()
        try:
            for _ in range(6):
                clock.now += TIMEOUT * 0.75
                watchdog.kick()
            clock.now += TIMEOUT * 0.999
            settle(watchdog)
            assert not latch.tripped, latch.reason
            assert not chip.all_off()
        finally:
            watchdog.close()

    def test_trips_when_the_timeout_has_passed_since_the_last_kick(self) -> None:
        clock, latch, watchdog, chip = self.make()
        watchdog.start()
        try:
            clock.now += 0.5 * TIMEOUT
            watchdog.kick()
            clock.now += TIMEOUT  # exactly the timeout since the kick: that is too late
            assert latch.wait(LIVENESS_S)
        finally:
            watchdog.close()
        assert latch.fault
        assert latch.reason == "watchdog: no tick for 0.250 s (timeout 0.250 s)"
        assert chip.all_off()

    def test_the_silence_named_is_measured_from_the_last_kick(self) -> None:
        clock, latch, watchdog, _chip = self.make()
        watchdog.start()
        try:
            watchdog.kick()
            clock.now += 3.5  # a long stall of the clock's process, seen at once
            assert latch.wait(LIVENESS_S)
        finally:
            watchdog.close()
        assert latch.reason == "watchdog: no tick for 3.500 s (timeout 0.250 s)"

    def test_start_counts_from_the_start_not_from_construction(self) -> None:
        clock, latch, watchdog, _chip = self.make()
        clock.now += 10.0  # a long warm-up between building the watchdog and starting it
        watchdog.start()
        try:
            settle(watchdog)
            assert not latch.tripped, latch.reason
            clock.now += TIMEOUT
            assert latch.wait(LIVENESS_S)
        finally:
            watchdog.close()
        assert latch.reason == "watchdog: no tick for 0.250 s (timeout 0.250 s)"

    def test_a_closed_watchdog_never_trips_and_its_thread_ends(self) -> None:
        clock, latch, watchdog, chip = self.make()
        watchdog.start()
        watchdog.close()
        assert not any(t.name == "jetbot-rt-watchdog" and t.is_alive()
                       for t in threading.enumerate())
        clock.now += 100 * TIMEOUT
        settle(watchdog)
        assert not latch.tripped
        assert not chip.all_off()

    def test_an_unstarted_watchdog_never_trips(self) -> None:
        clock, latch, _watchdog, _chip = self.make()
        clock.now += 100 * TIMEOUT
        settle(_watchdog)
        assert not latch.tripped

    def test_a_latch_tripped_elsewhere_ends_the_watchdog_with_the_first_reason(self) -> None:
        clock, latch, watchdog, chip = self.make()
        watchdog.start()
        latch.trip("SIGTERM received", fault=False)
        watchdog.kick()  # wakes the thread, which sees the latch and leaves
        clock.now += 100 * TIMEOUT
        settle(watchdog)
        watchdog.close()
        assert latch.reason == "SIGTERM received" and not latch.fault
        assert chip.all_off()


@pytest.fixture(autouse=True)
def _no_watchdog_thread_left() -> None:
    yield
    for thread in threading.enumerate():
        if thread.name == "jetbot-rt-watchdog":
            thread.join(LIVENESS_S)
            assert not thread.is_alive(), "a watchdog thread outlived its test"


class TestAnUntrippedLatch:
    def test_has_no_reason_time_or_fault(self) -> None:
        latch = SafeStopLatch()
        assert (latch.tripped, latch.reason, latch.t_trip, latch.fault) == (False, None, None,
                                                                            False)
        assert not latch.wait(0)
