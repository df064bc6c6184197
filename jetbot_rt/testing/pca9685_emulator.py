"""A register-level PCA9685 behind the ``smbus2.SMBus`` interface, for tests and dry runs.

It implements what our drivers and Adafruit's touch: MODE1/MODE2, PRE_SCALE (writes ignored
unless MODE1.SLEEP is set, as on the chip), the 16 LEDn_{ON,OFF}_{L,H} registers with
auto-increment (MODE1.AI), the ALL_LED registers (a write loads that register of every
channel; they read back as 0), and the full-on / full-off bits (full-off wins).

SLEEP, as the datasheet states it (MODE1, note 4: "When the oscillator is off (Sleep mode) the
LEDn outputs cannot be turned on, off or dimmed/blinked"): the outputs hold what they were
when the oscillator stopped, whatever is written to the LED registers while it sleeps (the
registers change, the outputs do not); waking makes the registers drive the outputs again.
This is the stricter of the two readings (the other: every output off while asleep): a
stop that put the chip to sleep before turning the outputs off would leave them on here.

With ``state_file`` the registers live in a small fixed-size binary file shared by every
process that opens it (``STATE``: registers, fault injection, counters). Each transaction
takes an ``flock`` on that file, reads it with one ``pread``, applies and writes it back in
place with one ``pwrite`` at offset 0: a few microseconds, no rename, no new inode, so a tick
never waits for a directory operation, and the file keeps the owner and mode it was created
with whoever writes it (a ``jetbot-rt stop`` run as root leaves it writable by the service's
user). The whole state is one write inside one page, which a SIGKILL cannot cut in two. A
lock held by a process that no longer runs (SIGSTOP) is waited for at most ``LOCK_WAIT_S``,
then the transaction fails like a bus that does not answer. The file is opened without
following a symbolic link and must be a regular file of exactly the state's size; one that
does not exist is created (by a root process: given to its directory's owner).
``--board-emulator <state file>`` (or ``[motors] emulator``) makes ``jetbot_rt.hal.i2c`` open
this instead of ``/dev/i2c-N``: tests and dry runs only, and announced (docs/HARDWARE.md).
The register map is ``jetbot_rt.hal.pca9685``, the drivers' own.

Fault injection (also through the file, so it reaches another process): ``fail_next`` makes
the next N transactions raise ``OSError(EREMOTEIO)``; ``absent`` makes the chip not answer.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
import struct
import time
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from smbus2 import i2c_msg
from smbus2.smbus2 import I2C_M_RD

from jetbot_rt.hal.pca9685 import (
    ALL_LED_OFF_H,
    ALL_LED_ON_L,
    CHANNELS,
    FULL_BIT,
    LAST_LED_REGISTER,
    LED0_ON_L,
    MODE1,
    MODE1_AI,
    MODE1_ALLCALL,
    MODE1_RESTART,
    MODE1_SLEEP,
    MODE2,
    OSCILLATOR_HZ,
    PRE_SCALE,
)

MAGIC = b"PCA9685E"
VERSION = 2
STATE = struct.Struct(f"<8sIHHB3xqQQ256s{CHANNELS}d{CHANNELS}d")
"""magic, version, address, register pointer, absent, fail_next, transactions, bytes,
the 256 registers, peak duty and held duty of each output."""
LOCK_WAIT_S = 2.0
"""A transaction waits at most this long for another's lock (a holder can only keep it this
long if it was stopped mid-transaction); then it fails as a bus that does not answer."""
_FLAGS = os.O_RDWR | os.O_CLOEXEC | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY


def _open_state(path: Path) -> int:
    """The state file, opened read-write without following a link; created if missing
    (never with ``O_CREAT`` on an existing file: Linux's ``protected_regular`` refuses that to
    root in a sticky directory such as /tmp when another user owns the file)."""
    try:
        fd = os.open(path, _FLAGS)
    except FileNotFoundError:
        try:
            fd = os.open(path, _FLAGS | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:  # another process created it just now
            fd = os.open(path, _FLAGS)
        else:
            _give_to_directory_owner(fd, path)
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OSError(errno.EINVAL, "not a regular file")
    return fd


def _give_to_directory_owner(fd: int, path: Path) -> None:
    """A file root creates for another user's board (a ``stop`` before any runtime) belongs to
    whoever owns its directory, so that user's runtime can still write it."""
    if os.geteuid() != 0:
        return
    try:
        parent = os.stat(path.parent)
        if parent.st_uid != 0:
            os.fchown(fd, parent.st_uid, parent.st_gid)
    except OSError:
        pass  # left to root: the runtime's open says why, if it ever matters


def _lock(fd: int) -> None:
    deadline = time.monotonic() + LOCK_WAIT_S
    delay = 0.00005
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() >= deadline:
                raise OSError(errno.ETIMEDOUT, f"the emulator's state file stayed locked "
                                               f"for {LOCK_WAIT_S:g} s") from None
            time.sleep(delay)
            delay = min(2 * delay, 0.001)


def power_on_registers() -> list[int]:
    """Register values after power-on reset (datasheet table 4)."""
    regs = [0] * 256
    regs[MODE1] = MODE1_SLEEP | MODE1_ALLCALL
    regs[MODE2] = 0x04
    regs[0x02], regs[0x03], regs[0x04] = 0xE2, 0xE4, 0xE8  # SUBADR1..3
    regs[0x05] = 0xE0  # ALLCALLADR
    for channel in range(CHANNELS):
        regs[LED0_ON_L + 4 * channel + 3] = FULL_BIT  # LEDn_OFF_H: full off
    regs[PRE_SCALE] = 0x1E  # 200 Hz
    return regs


@dataclass(frozen=True)
class ChannelOutput:
    """What one output pin does, decoded from its four registers and MODE1."""

    on_count: int
    off_count: int
    full_on: bool
    full_off: bool
    duty: float
    """Effective fraction of the period the output is high: 0 when full-off (which wins over
    full-on), 1 when full-on, else (off - on) mod 4096 / 4096; while the oscillator sleeps,
    what the output was when it stopped."""


class PCA9685Emulator:
    """One PCA9685 at ``address`` on an emulated bus; other addresses do not answer."""

    def __init__(self, address: int = 0x60, state_file: str | Path | None = None) -> None:
        self.address = address
        self.registers = power_on_registers()
        self.fail_next = 0
        self.absent = False
        self.transactions = 0
        self.bytes = 0
        self.peak_duty = [0.0] * CHANNELS
        """Highest effective duty each output has had: proves a pulse that is over by now."""
        self.held = [0.0] * CHANNELS
        """The outputs while the oscillator sleeps: what they were when it stopped."""
        self._pointer = 0
        self._state_file = Path(state_file) if state_file is not None else None
        self._fd: int | None = None
        self._closer: weakref.finalize | None = None
        if self._state_file is not None:
            with self._shared_state():
                pass  # creates the file with power-on state if it does not exist yet

    # ---- shared state ------------------------------------------------------------------

    def _state_fd(self) -> int:
        if self._fd is None:
            assert self._state_file is not None
            self._fd = _open_state(self._state_file)
            self._closer = weakref.finalize(self, os.close, self._fd)
        return self._fd

    @contextmanager
    def _shared_state(self) -> Iterator[None]:
        if self._state_file is None:
            yield
            return
        fd = self._state_fd()
        _lock(fd)
        try:
            data = os.pread(fd, STATE.size + 1, 0)
            if data:  # empty: just created, this instance's power-on state goes in
                self._load(data)
            try:
                yield
            finally:
                # also after a failed transaction: an injected failure is used up (and
                # counted) in the shared state too, not only in this process's copy
                os.pwrite(fd, self._pack(), 0)
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)

    def _load(self, data: bytes) -> None:
        if len(data) != STATE.size or not data.startswith(MAGIC):
            raise OSError(errno.EINVAL, f"not a PCA9685 emulator state file of version "
                                        f"{VERSION} ({len(data)} bytes); delete it")
        (_magic, version, self.address, self._pointer, absent, self.fail_next,
         self.transactions, self.bytes, registers, *duties) = STATE.unpack(data)
        if version != VERSION:
            raise OSError(errno.EINVAL, f"emulator state file of version {version}, not "
                                        f"{VERSION}; delete it")
        self.absent = bool(absent)
        self.registers = list(registers)
        self.peak_duty = list(duties[:CHANNELS])
        self.held = list(duties[CHANNELS:])

    def _pack(self) -> bytes:
        return STATE.pack(MAGIC, VERSION, self.address, self._pointer, self.absent,
                          self.fail_next, self.transactions, self.bytes, bytes(self.registers),
                          *self.peak_duty, *self.held)

    def refresh(self) -> PCA9685Emulator:
        """Re-read the shared state file (what another process wrote); returns self."""
        with self._shared_state():
            pass
        return self

    def update(self, **fields: Any) -> None:
        """Set fault-injection fields (``fail_next``, ``absent``) in the shared state."""
        with self._shared_state():
            for name, value in fields.items():
                if name not in ("fail_next", "absent"):
                    raise ValueError(f"not a fault-injection field: {name}")
                if type(value) is not (int if name == "fail_next" else bool) or value < 0:
                    raise ValueError(f"{name} must be a count or a bool, got {value!r}")
                setattr(self, name, value)

    # ---- the bus transactions (smbus2.SMBus interface) ---------------------------------

    def _transaction(self, address: int) -> None:
        """Count one bus transaction and raise the OSError a real adapter would."""
        self.transactions += 1
        if self.fail_next > 0:
            self.fail_next -= 1
            raise OSError(errno.EREMOTEIO, os.strerror(errno.EREMOTEIO))
        if self.absent or address != self.address:
            raise OSError(errno.EREMOTEIO, os.strerror(errno.EREMOTEIO))

    def i2c_rdwr(self, *messages: i2c_msg) -> None:
        with self._shared_state():
            self._transaction(messages[0].addr if messages else self.address)
            for message in messages:
                if message.addr != self.address or self.absent:
                    raise OSError(errno.EREMOTEIO, os.strerror(errno.EREMOTEIO))
                if message.flags & I2C_M_RD:
                    data = self._read(message.len)
                    for i, value in enumerate(data):
                        message.buf[i] = bytes((value,))
                    self.bytes += message.len
                else:
                    payload = bytes(message)
                    self._write(payload)
                    self.bytes += len(payload)

    def write_quick(self, i2c_addr: int, force: bool | None = None) -> None:
        with self._shared_state():
            self._transaction(i2c_addr)

    def close(self) -> None:
        """Closes the state file; the next transaction or ``refresh()`` opens it again."""
        if self._closer is not None:
            self._closer()
        self._fd = self._closer = None

    def __enter__(self) -> PCA9685Emulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- register semantics ------------------------------------------------------------

    def _next(self, register: int) -> int:
        if not self.registers[MODE1] & MODE1_AI:
            return register
        if register in (LAST_LED_REGISTER, 0xFF):
            return 0x00
        return register + 1

    def _write(self, payload: bytes) -> None:
        if not payload:
            return
        self._pointer = payload[0]
        for value in payload[1:]:
            self._store(self._pointer, value)
            self._pointer = self._next(self._pointer)
        self.peak_duty = [max(p, d) for p, d in zip(self.peak_duty, self.duties())]

    def _read(self, length: int) -> list[int]:
        values = []
        for _ in range(length):
            register = self._pointer
            values.append(0 if ALL_LED_ON_L <= register <= ALL_LED_OFF_H else
                          self.registers[register])
            self._pointer = self._next(register)
        return values

    def _store(self, register: int, value: int) -> None:
        regs = self.registers
        if register == MODE1:
            was_active = not regs[MODE1] & MODE1_SLEEP
            restart = regs[MODE1] & MODE1_RESTART
            if value & MODE1_RESTART:
                restart = 0  # writing 1 clears RESTART
            if value & MODE1_SLEEP and was_active:
                restart = MODE1_RESTART  # PWM was running when put to sleep
                self.held = self.duties()  # the outputs freeze as they are
            regs[MODE1] = (value & ~MODE1_RESTART & 0xFF) | restart
        elif register == PRE_SCALE:
            if regs[MODE1] & MODE1_SLEEP:
                regs[PRE_SCALE] = max(value, 3)  # the chip clamps values below 3 to 3
        elif ALL_LED_ON_L <= register <= ALL_LED_OFF_H:
            offset = register - ALL_LED_ON_L
            for channel in range(CHANNELS):
                regs[LED0_ON_L + 4 * channel + offset] = value
        elif register <= LAST_LED_REGISTER or register == 0xFF:
            regs[register] = value
        # 0x46..0xF9 are reserved: writes are ignored

    # ---- decoded views for tests and benchmarks ----------------------------------------

    @property
    def sleeping(self) -> bool:
        return bool(self.registers[MODE1] & MODE1_SLEEP)

    @property
    def frequency(self) -> float:
        return OSCILLATOR_HZ / 4096 / (self.registers[PRE_SCALE] + 1)

    def channel(self, index: int) -> ChannelOutput:
        base = LED0_ON_L + 4 * index
        on_l, on_h, off_l, off_h = self.registers[base : base + 4]
        on_count = ((on_h & 0x0F) << 8) | on_l
        off_count = ((off_h & 0x0F) << 8) | off_l
        full_on = bool(on_h & FULL_BIT)
        full_off = bool(off_h & FULL_BIT)
        if self.sleeping:
            duty = self.held[index]
        elif full_off:
            duty = 0.0
        elif full_on:
            duty = 1.0
        else:
            duty = ((off_count - on_count) % 4096) / 4096
        return ChannelOutput(on_count, off_count, full_on, full_off, duty)

    def duties(self) -> list[float]:
        """Effective duty of all 16 outputs."""
        return [self.channel(i).duty for i in range(CHANNELS)]

    def all_off(self) -> bool:
        return all(duty == 0.0 for duty in self.duties())
