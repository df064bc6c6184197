"""An I2C bus on Linux's i2c-dev (through smbus2) with the interface of CircuitPython's
``busio.I2C``, so Adafruit's drivers run on a Jetson without Blinka's board detection.

Every transaction is retried a bounded number of times on ``OSError`` (a motor's electrical
noise can make one transfer fail); one that keeps failing becomes an ``I2CFault`` naming the
bus and address, which the runtime turns into a safe stop.

A bus opened with ``emulator=<state file>`` (``--board-emulator``, ``[motors] emulator``) is
the register-level PCA9685 emulator of ``jetbot_rt.testing`` sharing its registers through that
file, for tests and dry runs only: chosen explicitly, never by the environment, and announced
by every command that uses it (``emulator_notice``: run's stdout and ``start`` event, check's
motor row, stop's stdout; never stderr, whose one line is a refusal's).
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

from jetbot_rt.errors import Fault, UsageError

if TYPE_CHECKING:
    import argparse
    from collections.abc import Callable

    from jetbot_rt.config.sections import MotorsConfig

RETRY_DELAY_S = 0.001
EMULATOR_FLAG = "--board-emulator"


class I2CFault(Fault):
    """An I2C transaction that kept failing after its retries."""


def add_emulator_argument(parser: argparse.ArgumentParser) -> None:
    """``--board-emulator STATE_FILE``, the same for run, check and stop."""
    parser.add_argument(
        EMULATOR_FLAG, metavar="STATE_FILE", dest="board_emulator",
        help="tests and dry runs: the register-level PCA9685 emulator whose registers live in "
             "STATE_FILE stands in for the motor board (overrides [motors] emulator)",
    )


def emulator_notice(state_file: str) -> str:
    """What a command says when its motor board is the emulator: no hardware is driven."""
    return f"the motor board is the PCA9685 EMULATOR in {state_file}, not I2C hardware"


def open_smbus(bus_number: int, emulated_address: int = 0x60, emulator: str | None = None
               ) -> Any:
    """``smbus2.SMBus(bus_number)``, or the PCA9685 emulator whose registers live in the file
    ``emulator``. Raises ``UsageError`` when the device node (or that file) cannot be opened."""
    if emulator:
        from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

        try:
            return PCA9685Emulator(address=emulated_address, state_file=emulator)
        except OSError as exc:
            raise UsageError(f"cannot open the PCA9685 emulator's state file {emulator}: "
                             f"{exc.strerror or exc}") from None
    try:
        from smbus2 import SMBus
    except ImportError:
        raise UsageError(
            "the real backend needs smbus2: pip install 'jetbot_rt[jetson]'"
        ) from None
    try:
        return SMBus(bus_number)
    except OSError as exc:
        raise UsageError(
            f"cannot open /dev/i2c-{bus_number}: {exc.strerror or exc} "
            "(is the bus enabled and is this user in the i2c group?)"
        ) from None


def _view(buffer: Any, start: int, end: int | None) -> memoryview:
    view = memoryview(buffer)
    return view[start : len(view) if end is None else end]


class I2CBus:
    """``busio.I2C``'s interface over an ``smbus2.SMBus``-like object (``i2c_rdwr``,
    ``write_quick``)."""

    def __init__(self, smbus: Any, bus_number: int, retries: int = 3, *,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.smbus = smbus
        self.bus_number = bus_number
        self.retries = retries
        self.sleep = sleep
        """Waits between retries (a test records them instead)."""
        self.retried = 0
        """Transfers that failed with ``OSError`` and were tried again (ridden-through noise
        and the failed attempts before an ``I2CFault`` alike): the run summary reports it."""
        self._lock = threading.Lock()
        self.owner: Any = None
        """The ``BoardLock`` of a bus opened to drive (``open_drive``); released by deinit."""

    @classmethod
    def open(cls, bus_number: int, retries: int = 3, emulated_address: int = 0x60,
             emulator: str | None = None) -> I2CBus:
        return cls(open_smbus(bus_number, emulated_address, emulator), bus_number, retries)

    @classmethod
    def for_motors(cls, motors: MotorsConfig) -> I2CBus:
        """The bus ``[motors]`` names: ``i2c_bus`` with ``i2c_retries``, or its emulator."""
        return cls.open(motors.i2c_bus, motors.i2c_retries, motors.address, motors.emulator)

    # ---- locking (busio.I2C) -----------------------------------------------------------

    def try_lock(self) -> bool:
        return self._lock.acquire(blocking=False)

    def unlock(self) -> None:
        self._lock.release()

    # ---- transfers (busio.I2C) ---------------------------------------------------------

    def writeto(self, address: int, buffer: Any, *, start: int = 0, end: int | None = None) -> None:
        data = bytes(_view(buffer, start, end))
        if not data:
            # A zero-length write is a probe (Adafruit's I2CDevice does this): SMBus quick write.
            self._retry(address, lambda: self.smbus.write_quick(address))
            return
        from smbus2 import i2c_msg

        self._retry(address, lambda: self.smbus.i2c_rdwr(i2c_msg.write(address, data)))

    def readfrom_into(
        self, address: int, buffer: Any, *, start: int = 0, end: int | None = None
    ) -> None:
        from smbus2 import i2c_msg

        target = _view(buffer, start, end)

        def read() -> None:
            message = i2c_msg.read(address, len(target))
            self.smbus.i2c_rdwr(message)
            target[:] = bytes(message)

        self._retry(address, read)

    def writeto_then_readfrom(
        self,
        address: int,
        buffer_out: Any,
        buffer_in: Any,
        *,
        out_start: int = 0,
        out_end: int | None = None,
        in_start: int = 0,
        in_end: int | None = None,
    ) -> None:
        """Write then read in one combined transaction (repeated start), as busio does."""
        from smbus2 import i2c_msg

        data = bytes(_view(buffer_out, out_start, out_end))
        target = _view(buffer_in, in_start, in_end)

        def transfer() -> None:
            write = i2c_msg.write(address, data)
            read = i2c_msg.read(address, len(target))
            self.smbus.i2c_rdwr(write, read)
            target[:] = bytes(read)

        self._retry(address, transfer)

    def transfer(self, address: int, writes: list[bytes], read: int = 0) -> bytes:
        """Several writes (and an optional read) in one combined transaction: repeated starts,
        no STOP between them, so no other master's transfer can land in between."""
        from smbus2 import i2c_msg

        result = b""

        def run() -> None:
            nonlocal result
            messages = [i2c_msg.write(address, data) for data in writes]
            if read:
                messages.append(i2c_msg.read(address, read))
            self.smbus.i2c_rdwr(*messages)
            result = bytes(messages[-1]) if read else b""

        self._retry(address, run)
        return result

    def scan(self) -> list[int]:
        found = []
        for address in range(0x03, 0x78):
            try:
                self.smbus.write_quick(address)
            except OSError:
                continue
            found.append(address)
        return found

    def deinit(self) -> None:
        self.smbus.close()
        if self.owner is not None:
            self.owner.release()
            self.owner = None

    def __enter__(self) -> I2CBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.deinit()

    # ---- retry -------------------------------------------------------------------------

    def _retry(self, address: int, transfer: Any) -> None:
        attempts = 1 + self.retries
        for attempt in range(1, attempts + 1):
            try:
                transfer()
                return
            except OSError as exc:
                if attempt == attempts:
                    raise I2CFault(
                        f"I2C bus {self.bus_number} address 0x{address:02x}: "
                        f"{exc.strerror or exc} (after {attempts} attempts, "
                        f"[motors] i2c_retries = {self.retries})"
                    ) from exc
                self.retried += 1
                self.sleep(RETRY_DELAY_S * attempt)
