"""The two JetBot motor boards, both a PCA9685 PWM chip on I2C driving H-bridges, and the
hardware stop they share.

- ``waveshare`` (Waveshare JetBot board), wired as NVIDIA's jetbot package drives it: left
  motor on channels (1, 0), right on (2, 3); forward puts the duty on the pair's first channel
  and full-off on the second, reverse the other way round, zero turns both off.
- ``adafruit_motorhat`` through Adafruit's ``MotorKit`` (TB6612 H-bridges; motorN is
  configurable per wheel).

The hardware stop is one write: ALL_LED_OFF_H (0xFD) <- full-off bit (0x10), which sets the
full-off bit of every output at once and takes precedence over any full-on or PWM setting.

``jetbot-rt stop`` also puts the chip to SLEEP, in the same combined transaction, after the
full-off: while the oscillator is off "the LEDn outputs cannot be turned on, off or
dimmed/blinked" (datasheet, MODE1 note 4), so a process that keeps writing duties to the LED
registers cannot drive the motors again; only a write to MODE1 (a drive being set up) wakes
it. A drive checks MODE1 in every write: a chip asleep that it did not put to sleep (a stop
from elsewhere, or a reset) is a ``Fault``, so that runtime ends in its safe stop.
"""

from __future__ import annotations

import sys
import time
import types
from typing import TYPE_CHECKING, Any

from jetbot_rt.errors import Fault, UsageError
from jetbot_rt.hal.base import Drive, finite_pair
from jetbot_rt.hal.i2c import I2CBus, I2CFault
from jetbot_rt.hal.pca9685 import (
    ALL_LED_OFF_H,
    FULL_BIT,
    LED0_ON_L,
    MODE1,
    MODE1_AI,
    MODE1_SLEEP,
    MODE2,
    MODE2_OUTDRV,
    OSCILLATOR_HZ,
    PRE_SCALE,
)

if TYPE_CHECKING:
    from jetbot_rt.config.sections import MotorsConfig


HARDWARE_STOP = bytes((ALL_LED_OFF_H, FULL_BIT))
SLEEP = bytes((MODE1, MODE1_SLEEP | MODE1_AI))


def hardware_stop(bus: I2CBus, address: int) -> None:
    """Turn every PCA9685 output off in one I2C write. Raises ``I2CFault``."""
    bus.writeto(address, HARDWARE_STOP)


def stop_and_sleep(bus: I2CBus, address: int) -> None:
    """Every output full-off, then the oscillator off, in one combined transaction (no other
    write can land between the two, which could leave an output held on). Raises ``I2CFault``."""
    bus.transfer(address, [HARDWARE_STOP, SLEEP])


class BoardAsleep(Fault):
    """The chip sleeps though this drive did not put it to sleep: another process stopped it
    (``jetbot-rt stop``) or it was reset.

    ``jetbot-rt stop`` puts the chip to sleep before it asks the runtime to end, so a tick can
    land in between: the loop gives that request 30 ms to arrive (the outputs are off, asleep)
    and ends in order if it does, as a fault if it does not."""

    STOP_REQUEST_GRACE_S = 0.03

    def __init__(self, bus: I2CBus, address: int) -> None:
        super().__init__(
            f"motor board on I2C bus {bus.bus_number} at 0x{address:02x} is asleep: stopped by "
            "another process (jetbot-rt stop) or reset"
        )


def _check_awake(mode1: int, bus: I2CBus, address: int) -> None:
    if mode1 & MODE1_SLEEP:
        raise BoardAsleep(bus, address)


def read_mode1(bus: I2CBus, address: int) -> int:
    """Read MODE1: proves a PCA9685-like chip answers at ``address``. Raises ``I2CFault``."""
    value = bytearray(1)
    bus.writeto_then_readfrom(address, bytes((MODE1,)), value)
    return value[0]


def prescale_for(frequency: float) -> int:
    return max(3, min(255, round(OSCILLATOR_HZ / (4096 * frequency)) - 1))


def _checked(left: float, right: float) -> tuple[float, float]:
    left, right = finite_pair(left, right)
    return max(-1.0, min(1.0, left)), max(-1.0, min(1.0, right))


def channel_registers(duty: float) -> bytes:
    """LEDn_ON_L, ON_H, OFF_L, OFF_H for a duty in [0, 1]: 0 is full-off, 1 is full-on."""
    count = round(duty * 4096)
    if count <= 0:
        return bytes((0, 0, 0, FULL_BIT))
    if count >= 4096:
        return bytes((0, FULL_BIT, 0, 0))
    return bytes((0, 0, count & 0xFF, count >> 8))


def channel_write(channel: int, duty: float) -> bytes:
    """One I2C write that sets output ``channel`` to ``duty`` (``channel_registers``)."""
    return bytes((LED0_ON_L + 4 * channel,)) + channel_registers(duty)


class BoardDrive(Drive):
    """What both motor boards share: a PCA9685 at ``address`` on ``bus``, stopped by the
    hardware stop (every output full-off, then sleep), the bus's retries as its stats."""

    def __init__(self, bus: I2CBus, address: int) -> None:
        self.bus = bus
        self.address = address
        hardware_stop(bus, address)

    def stop(self) -> None:
        hardware_stop(self.bus, self.address)

    def close(self) -> None:
        self.bus.deinit()

    def stats(self) -> dict[str, float]:
        return {"i2c_retried": self.bus.retried}


class WaveshareDrive(BoardDrive):
    """Registers written directly: all four motor channels (0..3, contiguous) in one
    auto-increment write, so both wheels change together at the write's STOP condition and
    no channel is ever seen half-updated (one transaction, 17 bytes, per tick)."""

    LEFT = (1, 0)  # (forward channel, reverse channel)
    RIGHT = (2, 3)
    CHANNELS = 4

    def __init__(self, bus: I2CBus, address: int, pwm_frequency: float) -> None:
        super().__init__(bus, address)
        bus.writeto(address, bytes((MODE1, MODE1_SLEEP | MODE1_AI)))  # PRE_SCALE needs SLEEP
        bus.writeto(address, bytes((PRE_SCALE, prescale_for(pwm_frequency))))
        bus.writeto(address, bytes((MODE2, MODE2_OUTDRV)))
        bus.writeto(address, bytes((MODE1, MODE1_AI)))  # wake; ALLCALL off
        time.sleep(0.0005)  # oscillator start-up (datasheet: 500 us)

    def write(self, left: float, right: float) -> None:
        left, right = _checked(left, right)
        duties = [0.0] * self.CHANNELS
        for (forward, reverse), duty in ((self.LEFT, left), (self.RIGHT, right)):
            duties[forward if duty > 0 else reverse] = abs(duty)
        payload = bytes((LED0_ON_L,)) + b"".join(channel_registers(d) for d in duties)
        # The duties, then MODE1 read back, in one transaction: asleep, the chip holds its
        # outputs off whatever the LED registers say, and this drive must stop.
        mode1 = self.bus.transfer(self.address, [payload, bytes((MODE1,))], read=1)
        if any(duties):
            _check_awake(mode1[0], self.bus, self.address)


# The MotorHAT's TB6612 PWM (enable) input for each of MotorKit's motors.
MOTORHAT_PWM_CHANNEL = {1: 8, 2: 13, 3: 2, 4: 7}


def _import_motorkit() -> Any:
    # adafruit_motorkit runs ``import board`` at import time, which makes Blinka detect the
    # board and raise on one it does not know (a new Jetson, a CI machine). We always pass
    # our own bus object, so ``board`` is never used: a placeholder module lets the import
    # succeed. The same goes for ``busio``, whose I2C and SPI Adafruit's modules import for
    # type hints that are evaluated at import time.
    for name in ("board", "busio"):
        try:
            __import__(name)
        except Exception:
            placeholder = types.ModuleType(name)
            placeholder.I2C = I2CBus  # type: ignore[attr-defined]
            placeholder.SPI = type("SPI", (), {})  # type: ignore[attr-defined]
            sys.modules[name] = placeholder
    from adafruit_motorkit import MotorKit

    return MotorKit


class MotorHatDrive(BoardDrive):
    """Adafruit DC & Stepper Motor HAT through ``MotorKit``. Zero is throttle ``None`` (both
    H-bridge inputs off, as the hardware stop leaves them), not MotorKit's brake."""

    def __init__(
        self, bus: I2CBus, address: int, pwm_frequency: float, left_motor: int, right_motor: int
    ) -> None:
        if left_motor == right_motor:
            raise UsageError(
                f"[motors] left_motor and right_motor must differ, both are {left_motor}"
            )
        super().__init__(bus, address)
        motorkit_class = _import_motorkit()
        self.kit = motorkit_class(address=address, i2c=bus, pwm_frequency=pwm_frequency)
        self._motor_numbers = (left_motor, right_motor)
        self._motors = tuple(getattr(self.kit, f"motor{n}") for n in self._motor_numbers)
        self._enables_off = False

    def write(self, left: float, right: float) -> None:
        duties = _checked(left, right)
        if any(duties):
            _check_awake(read_mode1(self.bus, self.address), self.bus, self.address)
        if self._enables_off and any(duties):
            # The hardware stop also turned off the PWM (enable) inputs MotorKit set once.
            for number in self._motor_numbers:
                self.bus.writeto(self.address, channel_write(MOTORHAT_PWM_CHANNEL[number], 1.0))
            self._enables_off = False
        for motor, duty in zip(self._motors, duties):
            motor.throttle = duty if duty != 0 else None

    def stop(self) -> None:
        super().stop()
        self._enables_off = True


def open_drive(motors: MotorsConfig) -> Drive:
    """Open the bus, check the board answers, and set it up (all outputs off).

    Raises ``UsageError`` when the bus cannot be opened or nothing answers at the address
    (the motors were never moved), ``I2CFault`` when the board fails during set-up.
    """
    from jetbot_rt.hal.ownership import BoardLock

    owner = BoardLock.acquire(motors.i2c_bus, motors.emulator, motors.address)  # before any write
    try:
        bus = I2CBus.for_motors(motors)
    except BaseException:
        owner.release()
        raise
    bus.owner = owner
    try:
        read_mode1(bus, motors.address)
    except I2CFault as exc:
        bus.deinit()
        raise UsageError(
            f"no motor board ({motors.layout}) answers on I2C bus {motors.i2c_bus} at "
            f"address 0x{motors.address:02x}: {exc.__cause__}"
        ) from None
    try:
        if motors.layout == "adafruit_motorhat":
            return MotorHatDrive(
                bus, motors.address, motors.pwm_frequency, motors.left_motor, motors.right_motor
            )
        return WaveshareDrive(bus, motors.address, motors.pwm_frequency)
    except BaseException:
        bus.deinit()
        raise
