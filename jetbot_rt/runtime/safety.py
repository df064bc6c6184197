"""The safe-stop latch, the drive guard that enforces it, and the watchdog thread that trips it.

Once the latch is tripped, every later non-zero write is refused, whichever thread makes it:
a queued callback or a late tick cannot restart a motor after a stop.

A zero write that fails (an I2C error burst longer than the bus's own retries) is tried again
and again for up to ``STOP_RETRY_S`` from its first failure before the stop gives up: while
the bus fails the wheels keep their last duty whatever we do, so trying costs nothing but
time at the exit. The drive says whether the board confirmed the zero (``motors_line``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from jetbot_rt.hal.base import Drive

STOP_LOCK_TIMEOUT_S = 0.05
"""How long a stop waits for a drive write in flight (an I2C write takes well under 1 ms)."""
STOP_RETRY_S = 1.0
"""How long a failing zero write is tried again, from its first failure, before the stop is
reported NOT confirmed. Long enough for a burst of hundreds of failed transfers (a loose
connector, a motor's electrical noise) and short enough that the runtime's exit, and
systemd's ExecStopPost after it, come well within the unit's 2 s WatchdogSec."""
STOP_RETRY_PAUSE_S = 0.002
"""Pause between two failed zero writes (each already tries the bus 1 + i2c_retries times)."""


class SafeStopLatch:
    """Trips once; the first reason wins. ``on_trip`` callbacks run in the tripping thread."""

    def __init__(self) -> None:
        self._tripped = threading.Event()
        self._lock = threading.Lock()
        self.reason: str | None = None
        self.fault = False
        self.t_trip: float | None = None
        self._callbacks: list[Callable[[str], None]] = []

    @property
    def tripped(self) -> bool:
        return self._tripped.is_set()

    def on_trip(self, callback: Callable[[str], None]) -> None:
        self._callbacks.append(callback)

    def trip(self, reason: str, *, fault: bool = True) -> bool:
        """Latch the stop. ``fault`` False for an orderly end (signal, duration). Returns True
        for the call that actually tripped it."""
        if self._tripped.is_set():
            return False
        with self._lock:
            if self._tripped.is_set():
                return False
            self.reason = reason
            self.fault = fault
            self.t_trip = time.monotonic()
            self._tripped.set()
        for callback in self._callbacks:
            callback(reason)
        return True

    def wait(self, timeout: float | None = None) -> bool:
        return self._tripped.wait(timeout)


class GuardedDrive:
    """Wraps a backend ``Drive``: after the latch, only zero goes through.

    Writes are serialised by one lock, and the latch's zero write takes the same lock after the
    flag is set, so no write that started before the trip can land after the zero.
    """

    def __init__(self, drive: Drive, latch: SafeStopLatch, retry_s: float = STOP_RETRY_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.drive = drive
        self.latch = latch
        self.retry_s = retry_s
        self.clock = clock
        self._lock = threading.Lock()
        self._stopping = False
        """A stop holds the lock while it retries: another stop waits for it (bounded)."""
        self.refused = 0
        self.stop_errors: list[str] = []
        self.zero_confirmed: bool | None = None
        """Whether a zero write reached the board after the last non-zero write (None: none
        tried yet). Once it has, nothing but zero can reach the board while the latch holds."""
        self.failed_stops = 0
        """Zero writes that failed since the last one that reached the board."""
        self._t_failing: float | None = None
        self._failing_s = 0.0
        self._last_error = ""
        self.recovered: tuple[int, float] | None = None
        """(failed zero writes, seconds) of the last run of failures a zero write ended."""
        latch.on_trip(lambda _reason: self.stop())

    def write(self, left: float, right: float) -> bool:
        """Returns False (and writes nothing) when the latch refuses a non-zero command."""
        with self._lock:
            moving = left != 0.0 or right != 0.0
            if moving and self.latch.tripped:
                self.refused += 1
                return False
            if moving:
                self.zero_confirmed = False  # even a failed write may have reached the board
            self.drive.write(left, right)
            # The bus works: a zero write that fails later starts a new retry window.
            self.failed_stops, self._t_failing = 0, None
            if moving and self.latch.tripped:
                # The latch tripped while this write was in the driver, and its stop may not
                # have waited for it (``stop``): this write may have landed after the zero.
                self.zero_confirmed = False
                self._stop_until_confirmed()
            return True

    def stop(self) -> None:
        """Zero the motors by the drive's most direct means; never raises.

        Waits a bounded time for a write in flight; if that write hangs (an I2C transfer
        stuck in the driver), the stop goes out anyway: the kernel serialises the bus. A stop
        already retrying in another thread is waited for until its retry window ends."""
        locked = self._lock.acquire(timeout=STOP_LOCK_TIMEOUT_S)
        if not locked and self._stopping:
            locked = self._lock.acquire(timeout=self._retry_left() + STOP_LOCK_TIMEOUT_S)
        try:
            if not locked:
                self.stop_errors.append("a drive write in flight did not return; stopped anyway")
            self._stop_until_confirmed()
        finally:
            if locked:
                self._lock.release()

    def _retry_left(self) -> float:
        if self._t_failing is None:
            return self.retry_s
        return max(0.0, self._t_failing + self.retry_s - self.clock())

    def _stop_until_confirmed(self) -> None:
        """The zero write, again after each failure until it reaches the board or
        ``retry_s`` has passed since the first failure (then one attempt per call; one
        attempt too where a zero already reached the board after the last non-zero write)."""
        self._stopping = True
        try:
            while True:
                t_attempt = self.clock()
                try:
                    self.drive.stop()
                except Exception as exc:  # the stop must not be lost to an exception; report it
                    if self._t_failing is None:
                        self._t_failing = t_attempt
                    self.failed_stops += 1
                    self.zero_confirmed = bool(self.zero_confirmed)  # None: never confirmed
                    self._last_error = f"{type(exc).__name__}: {exc}"
                    self._failing_s = self.clock() - self._t_failing
                    left = self.retry_s - self._failing_s
                    if self.zero_confirmed or left <= 0:
                        break
                    time.sleep(min(STOP_RETRY_PAUSE_S, left))
                    continue
                if self._t_failing is not None:
                    self.recovered = (self.failed_stops, self.clock() - self._t_failing)
                self.failed_stops, self._t_failing = 0, None
                self.zero_confirmed = True
                return
            if self._last_error not in self.stop_errors:
                self.stop_errors.append(self._last_error)
        finally:
            self._stopping = False

    def motors_line(self) -> str | None:
        """Whether the board confirmed the zero, for the summary and the ``end`` event."""
        if self.zero_confirmed is None:
            return None
        if not self.zero_confirmed:
            return (f"NOT confirmed zero after {self.failed_stops} failed zero writes in "
                    f"{self._failing_s:.2f} s: {self._last_error}")
        if self.recovered is not None:
            failed, seconds = self.recovered
            return f"confirmed zero after {failed} failed zero writes in {seconds:.3f} s"
        return "confirmed zero"


class Watchdog:
    """A thread with its own monotonic clock: no ``kick()`` within ``timeout`` -> trip the latch.

    It sleeps exactly until the current deadline instead of polling, so the stop lands within
    the timeout plus the scheduler's wake-up latency.
    """

    def __init__(self, latch: SafeStopLatch, timeout: float,
                 clock: Callable[[], float] = time.monotonic,
                 key: str = "[loop] watchdog_timeout") -> None:
        self.latch = latch
        self.timeout = timeout
        self.key = key
        """The setting that changes ``timeout``, named in the trip's reason."""
        self.clock = clock
        self._last_kick = clock()
        self._kicked = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="jetbot-rt-watchdog", daemon=True)

    def start(self) -> None:
        self.kick()
        self._thread.start()

    def kick(self) -> None:
        with self._kicked:
            self._last_kick = self.clock()
            self._kicked.notify()

    def close(self) -> None:
        with self._kicked:
            self._stopped = True
            self._kicked.notify()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=1.0)

    def _run(self) -> None:
        with self._kicked:
            while not self._stopped and not self.latch.tripped:
                remaining = self._last_kick + self.timeout - self.clock()
                if remaining > 0:
                    self._kicked.wait(remaining)
                    continue
                silence = self.clock() - self._last_kick
                break
            else:
                return
        self.latch.trip(f"watchdog: no tick for {silence:.3f} s "
                        f"(limit {self.key} = {self.timeout:.3g} s)")

