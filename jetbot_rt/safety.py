"""The safe-stop latch, the drive guard that enforces it, and the watchdog thread that trips it.

Once the latch is tripped, every later non-zero write is refused, whichever thread makes it:
a queued callback or a late tick cannot restart a motor after a stop.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from jetbot_rt.hal.base import Drive

STOP_LOCK_TIMEOUT_S = 0.05
"""How long a stop waits for a drive write in flight (an I2C write takes well under 1 ms)."""


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

    def __init__(self, drive: Drive, latch: SafeStopLatch) -> None:
        self.drive = drive
        self.latch = latch
        self._lock = threading.Lock()
        self.refused = 0
        self.stop_errors: list[str] = []
        latch.on_trip(lambda _reason: self.stop())

    def write(self, left: float, right: float) -> bool:
        """Returns False (and writes nothing) when the latch refuses a non-zero command."""
        with self._lock:
            if self.latch.tripped and (left != 0.0 or right != 0.0):
                self.refused += 1
                return False
            self.drive.write(left, right)
            return True

    def stop(self) -> None:
        """Zero the motors by the drive's most direct means; never raises.

        Waits a bounded time for a write in flight; if that write hangs (an I2C transfer
        stuck in the driver), the stop goes out anyway: the kernel serialises the bus."""
        locked = self._lock.acquire(timeout=STOP_LOCK_TIMEOUT_S)
        try:
            if not locked:
                self.stop_errors.append("a drive write in flight did not return; stopped anyway")
            try:
                self.drive.stop()
            except Exception as exc:  # the stop must not be lost to an exception; report it
                self.stop_errors.append(f"{type(exc).__name__}: {exc}")
        finally:
            if locked:
                self._lock.release()


class Watchdog:
    """A thread with its own monotonic clock: no ``kick()`` within ``timeout`` -> trip the latch.

    It sleeps exactly until the current deadline instead of polling, so the stop lands within
    the timeout plus the scheduler's wake-up latency.
    """

    def __init__(self, latch: SafeStopLatch, timeout: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.latch = latch
        self.timeout = timeout
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
        self.latch.trip(f"watchdog: no tick for {silence:.3f} s (timeout {self.timeout:.3f} s)")

