"""The latch, the guarded drive and the watchdog against the bugs that slip past end-to-end
runs: a write racing the latch's callbacks, a stop stuck behind a hung write, the watchdog's
deadline arithmetic. The drive is the Waveshare driver on the register-level PCA9685 emulator;
the watchdog runs its real thread on a clock the test moves by hand.
"""

from __future__ import annotations

import threading

import pytest
from runner import wait_for

from jetbot_rt.hal.i2c import I2CBus
from jetbot_rt.hal.motors import WaveshareDrive
from jetbot_rt.runtime.safety import GuardedDrive, SafeStopLatch, Watchdog
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
        assert latch.reason == ("watchdog: no tick for 0.250 s "
                                "(limit [loop] watchdog_timeout = 0.25 s)")
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
        assert latch.reason == ("watchdog: no tick for 3.500 s "
                                "(limit [loop] watchdog_timeout = 0.25 s)")

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
        assert latch.reason == ("watchdog: no tick for 0.250 s "
                                "(limit [loop] watchdog_timeout = 0.25 s)")

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


# ---- a zero write that fails: tried again for a bounded time, and said ---------------------

BURST_ERROR = ("I2CFault: I2C bus 1 address 0x60: Remote I/O error (after 4 attempts, "
               "[motors] i2c_retries = 3)")


class SteppingClock:
    """A clock that moves 1/64 s each time it is read: the retry window is counted in reads,
    the same on a loaded machine as on an idle one (1/64 is exact in binary)."""

    STEP = 1 / 64

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        self.now += self.STEP
        return self.now


RETRY_S = 17 / 64
"""A failed zero write reads the clock twice: the 9th ends exactly 17 steps after the 1st
began, so the window is over there (and not one write later)."""
WRITES_IN_WINDOW = 9


def stepping_drive() -> tuple[PCA9685Emulator, SafeStopLatch, GuardedDrive]:
    chip, drive = emulated_drive()
    latch = SafeStopLatch()
    guarded = GuardedDrive(drive, latch, retry_s=RETRY_S, clock=SteppingClock())
    assert guarded.zero_confirmed is None and guarded.motors_line() is None
    assert guarded.write(0.5, -0.5)
    assert guarded.zero_confirmed is False  # a motor may turn
    return chip, latch, guarded


class TestAZeroWriteThatFailsIsTriedAgain:
    """An I2C error burst longer than the bus's retries (1 + 3 transfers per zero write) must
    not leave the wheels at their last duty: the stop keeps writing zero until the board takes
    it or ``retry_s`` has passed, and says which."""

    @pytest.mark.parametrize("burst", [20, 60])
    def test_a_burst_longer_than_the_retries_ends_at_zero_and_is_said(self, burst: int) -> None:
        chip, drive = emulated_drive()
        latch = SafeStopLatch()
        guarded = GuardedDrive(drive, latch)  # the runtime's: STOP_RETRY_S, the real clock
        assert guarded.write(0.5, -0.5)
        chip.fail_next = burst
        assert latch.trip("I2C burst")
        assert chip.all_off(), chip.duties()
        assert chip.fail_next == 0
        assert guarded.zero_confirmed is True
        assert guarded.stop_errors == []
        line = guarded.motors_line()
        assert line is not None
        assert line.startswith(f"confirmed zero after {burst // 4} failed zero writes in "), line
        # the latch holds: nothing but zero from now on
        assert not guarded.write(0.4, 0.4)
        assert chip.all_off()

    def test_a_bus_that_never_comes_back_is_tried_for_the_window_and_not_confirmed(self) -> None:
        chip, latch, guarded = stepping_drive()
        chip.absent = True
        assert latch.trip("bus gone")
        assert not chip.all_off(), "the board cannot have been reached"
        assert guarded.failed_stops == WRITES_IN_WINDOW
        assert guarded.zero_confirmed is False
        assert guarded.motors_line() == (
            f"NOT confirmed zero after {WRITES_IN_WINDOW} failed zero writes in "
            f"{RETRY_S:.2f} s: {BURST_ERROR}")
        assert guarded.stop_errors == [BURST_ERROR]
        # the window is over: a later stop (the exit path's) tries once, and says it once
        guarded.stop()
        assert guarded.failed_stops == WRITES_IN_WINDOW + 1
        assert guarded.stop_errors == [BURST_ERROR]
        # the bus is back: the next stop reaches the board and says what it took
        chip.absent = False
        guarded.stop()
        assert chip.all_off(), chip.duties()
        assert guarded.zero_confirmed is True and guarded.failed_stops == 0
        line = guarded.motors_line()
        assert line is not None
        assert line.startswith(f"confirmed zero after {WRITES_IN_WINDOW + 1} failed zero "
                               "writes in "), line
        assert not guarded.write(0.1, 0.1)

    def test_a_working_write_between_two_failing_stops_opens_a_new_window(self) -> None:
        chip, _latch, guarded = stepping_drive()
        chip.absent = True
        guarded.stop()  # not latched: the drive stays usable
        assert guarded.failed_stops == WRITES_IN_WINDOW
        chip.absent = False
        assert guarded.write(0.2, 0.2)
        assert guarded.failed_stops == 0 and guarded.zero_confirmed is False
        chip.absent = True
        guarded.stop()
        assert guarded.failed_stops == WRITES_IN_WINDOW, "the new failures got no window"

    def test_a_zero_the_board_took_stays_confirmed_and_is_not_insisted_on(self) -> None:
        chip, latch, guarded = stepping_drive()
        assert latch.trip("test")
        assert guarded.zero_confirmed is True and guarded.motors_line() == "confirmed zero"
        chip.absent = True  # the board stops answering: what it last got from us was zero
        guarded.stop()
        assert guarded.failed_stops == 1, "it insisted on a zero the board already had"
        assert guarded.zero_confirmed is True and guarded.motors_line() == "confirmed zero"
        assert guarded.stop_errors == [BURST_ERROR]

    def test_a_drive_whose_first_zero_fails_is_not_confirmed(self) -> None:
        chip, drive = emulated_drive()
        guarded = GuardedDrive(drive, SafeStopLatch(), retry_s=RETRY_S, clock=SteppingClock())
        chip.absent = True
        guarded.stop()
        assert guarded.zero_confirmed is False
        assert (guarded.motors_line() or "").startswith("NOT confirmed zero after 9 ")

    def test_a_stop_while_another_retries_waits_for_it_instead_of_going_around_it(
            self) -> None:
        chip, drive = emulated_drive()
        latch = SafeStopLatch()
        guarded = GuardedDrive(drive, latch, retry_s=0.5)
        assert guarded.write(0.5, 0.5)
        chip.absent = True
        tripper = threading.Thread(target=latch.trip, args=("bus gone",), daemon=True)
        tripper.start()
        assert wait_for(lambda: guarded.failed_stops >= 1, LIVENESS_S) is not None
        guarded.stop()  # the exit path's stop, while the trip's still retries
        tripper.join(LIVENESS_S)
        assert not tripper.is_alive()
        assert "a drive write in flight did not return; stopped anyway" not in \
            guarded.stop_errors, guarded.stop_errors
        assert guarded.zero_confirmed is False




class LandingHangingDrive(HangingWriteDrive):
    """A write stuck in the driver that, once released, does reach the board: late. With
    ``vanish``, the board stops answering right after it."""

    def __init__(self, bus: I2CBus, chip: PCA9685Emulator, vanish: bool) -> None:
        super().__init__(bus)
        self.chip = chip
        self.vanish = vanish

    def write(self, left: float, right: float) -> None:
        hung = self.hang.is_set()
        if hung:
            self.in_write.set()
            self.release.wait(LIVENESS_S)
        WaveshareDrive.write(self, left, right)
        self.chip.absent = hung and self.vanish


@pytest.mark.parametrize("vanish", [False, True], ids=["bus-works", "bus-gone-after-it"])
def test_a_write_that_lands_after_the_stop_it_did_not_wait_for_is_zeroed_again(
        vanish: bool) -> None:
    chip = PCA9685Emulator(0x60)
    drive = LandingHangingDrive(I2CBus(chip, 1), chip, vanish)
    latch = SafeStopLatch()
    guarded = GuardedDrive(drive, latch, retry_s=RETRY_S, clock=SteppingClock())
    assert guarded.write(0.5, -0.5)
    drive.hang.set()
    writer = threading.Thread(target=guarded.write, args=(0.6, 0.6), daemon=True)
    writer.start()
    assert drive.in_write.wait(LIVENESS_S)
    latch.trip("test")  # its stop goes out around the hung write
    assert chip.all_off() and guarded.zero_confirmed is True
    drive.hang.clear()
    drive.release.set()
    writer.join(LIVENESS_S)
    assert not writer.is_alive()
    if vanish:  # the late write is on the board and no zero can follow it: said so
        assert not chip.all_off()
        assert guarded.zero_confirmed is False
        assert (guarded.motors_line() or "").startswith("NOT confirmed zero after 9 ")
    else:
        assert chip.all_off(), f"the late write stayed on the board: {chip.duties()}"
        assert guarded.zero_confirmed is True


class TestWhatTheStopSaysOnAnyClock:
    """The seconds the stop reports are differences on the drive's clock, whatever its origin
    (a monotonic clock may start anywhere: at boot, at 0, at a large value)."""

    def test_a_recovered_stop_names_the_seconds_from_its_first_failure(self) -> None:
        chip, latch, guarded = stepping_drive()
        chip.fail_next = 8  # two zero writes of four transfers each fail, the third lands
        assert latch.trip("burst")
        assert chip.all_off()
        # reads: 1st attempt (start, failure), 2nd (start, failure), 3rd start, its success:
        # five steps after the first failure began
        assert guarded.motors_line() == "confirmed zero after 2 failed zero writes in 0.078 s"

    def test_a_drive_that_moved_and_was_never_stopped_says_its_zero_is_not_confirmed(
            self) -> None:
        _chip, drive = emulated_drive()
        guarded = GuardedDrive(drive, SafeStopLatch(), retry_s=RETRY_S, clock=SteppingClock())
        assert guarded.write(0.3, 0.3)
        assert guarded.motors_line() == "NOT confirmed zero after 0 failed zero writes in 0.00 s: "

    def test_the_watchdogs_silence_is_measured_from_the_last_kick_on_a_clock_near_zero(
            self) -> None:
        clock = ManualClock(start=2.0)
        latch = SafeStopLatch()
        watchdog = Watchdog(latch, TIMEOUT, clock=clock)
        watchdog.start()
        try:
            clock.now += 3.5
            assert latch.wait(LIVENESS_S)
        finally:
            watchdog.close()
        assert latch.reason == ("watchdog: no tick for 3.500 s "
                                "(limit [loop] watchdog_timeout = 0.25 s)")


class StopStuckOnceDrive(WaveshareDrive):
    """The Waveshare driver whose first zero write fails and whose second blocks in the
    "driver" until released (an I2C transfer stuck in the kernel); later ones reach the chip."""

    def __init__(self, bus: I2CBus) -> None:
        super().__init__(bus, 0x60, 1600.0)
        self.stops = 0
        self.in_stop = threading.Event()
        self.release = threading.Event()

    def stop(self) -> None:
        self.stops += 1
        if self.stops == 1:
            raise OSError(121, "Remote I/O error")
        if self.stops == 2:
            self.in_stop.set()
            self.release.wait(LIVENESS_S * 6)
            return
        super().stop()


def test_a_stop_behind_a_retrying_stop_stuck_in_the_driver_waits_only_for_its_window() -> None:
    """The second stop waits for the first one's retry window (counted on the drive's clock
    from the first failure), then goes out anyway: the zero reaches the board while the first
    is still stuck."""
    chip = PCA9685Emulator(0x60)
    drive = StopStuckOnceDrive(I2CBus(chip, 1))
    clock = ManualClock(start=1000.0)
    guarded = GuardedDrive(drive, SafeStopLatch(), retry_s=0.5, clock=clock)
    assert guarded.write(0.5, 0.5)
    first = threading.Thread(target=guarded.stop, daemon=True)
    first.start()
    try:
        assert drive.in_stop.wait(LIVENESS_S)
        clock.now += 0.5  # the window since the first failure is over
        second = threading.Thread(target=guarded.stop, daemon=True)
        second.start()
        second.join(LIVENESS_S)  # only catches a hang: the window is over, it waits ~0.05 s
        assert not second.is_alive(), "the second stop waited past the first one's window"
        assert chip.all_off(), chip.duties()
        assert "a drive write in flight did not return; stopped anyway" in guarded.stop_errors
    finally:
        drive.release.set()
        first.join(LIVENESS_S)


def test_a_watchdog_left_running_does_not_keep_its_process_alive() -> None:
    """A process that ends without closing its watchdog (an uncaught error on the way out)
    exits at once: the watchdog's thread neither holds the interpreter open until its
    timeout nor trips the latch during the exit."""
    import subprocess
    import sys

    script = ("from jetbot_rt.runtime.safety import SafeStopLatch, Watchdog\n"
              "latch = SafeStopLatch()\n"
              "latch.on_trip(lambda reason: print('tripped', reason, flush=True))\n"
              "Watchdog(latch, 3600.0).start()\n"
              "print('started', flush=True)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            timeout=30)  # only catches a hang (the timeout is an hour)
    assert result.returncode == 0, result.stderr
    assert result.stdout == "started\n"
