"""``--input gamepad``: a Linux joystick device (``/dev/input/jsN``) read through the kernel's
joystick API (``linux/joystick.h``): 8-byte ``js_event`` records, unpacked with ``struct``.

Why the joystick API and not evdev: it needs nothing but the standard library on the robot's
Python 3.8 (python-evdev is a C extension with no wheel for the Jetson's aarch64 Python 3.8,
so it would need a compiler on the robot), the kernel's joydev driver is loaded for every USB
or Bluetooth pad (xpad, hid-sony, hid-nintendo, hid-generic), it numbers axes and buttons
densely and scales every axis to -32767..32767 with its calibration applied, and it reports
the pad's current state when the device is opened (``JS_EVENT_INIT``). evdev would add force
feedback and exclusive grabs, which driving does not need.

Mapping (``GamepadMap``, the layout of an Xbox-style pad under xpad/hid): hold the dead-man
button (LB, button 4) to drive with the left stick (axis 1 up = forward, axis 0 = turn);
hold RB (button 5) to brake (a zero command that, while a policy drives, takes over: the
policy is stopped). Releasing LB releases at once (the kernel's button event); a pad that is
unplugged (or a Bluetooth pad the kernel drops) gives a read error, a lost input. The kernel
sends events only on change, so while the dead-man button is held the reader renews the
command every ``POLL_S``: the deadman then guards a reader that stops, not the pad.

Limit: a Bluetooth pad that goes silent out of range stays "present" until the kernel drops
the link (the Bluetooth supervision timeout, seconds); until then its last state holds.
"""

from __future__ import annotations

import errno
import fcntl
import os
import select
import stat
import struct
import threading
from dataclasses import dataclass

from jetbot_rt.errors import UsageError
from jetbot_rt.teleop.hand import DEADMAN_S, HandCommand, HandInput

EVENT = struct.Struct("<IhBB")
"""``struct js_event``: u32 time (ms), s16 value, u8 type, u8 number."""
JS_EVENT_BUTTON = 0x01
JS_EVENT_AXIS = 0x02
JS_EVENT_INIT = 0x80
AXIS_FULL = 32767.0
JSIOCGVERSION = 0x80046A01
"""``_IOR('j', 0x01, __u32)``: every joystick device answers it; /dev/zero, a tty or an evdev
node (``/dev/input/eventN``, 24-byte records that would read as garbage ``js_event``s) do not."""
POLL_S = 0.05
DEAD_ZONE = 0.08
"""Stick values closer to the centre than this (a fraction of full travel) are zero."""


@dataclass(frozen=True)
class GamepadMap:
    forward_axis: int = 1
    turn_axis: int = 0
    deadman_button: int = 4
    brake_button: int = 5


def _shaped(value: float) -> float:
    return 0.0 if abs(value) < DEAD_ZONE else max(-1.0, min(1.0, value))


def _is_joystick(fd: int) -> bool:
    try:
        fcntl.ioctl(fd, JSIOCGVERSION, b"\0" * 4)
    except OSError:
        return False
    return True


class GamepadInput(HandInput):
    name = "gamepad"

    def __init__(self, path: str, deadman_s: float = DEADMAN_S,
                 mapping: GamepadMap = GamepadMap()) -> None:
        super().__init__(deadman_s)
        self.path = path
        self.mapping = mapping
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOCTTY)
        except OSError as exc:
            raise UsageError(f"--gamepad-device {path}: {exc.strerror or exc} (is the pad "
                             "connected? ls /dev/input/js*)") from None
        mode = os.fstat(fd).st_mode
        if not (stat.S_ISCHR(mode) or stat.S_ISFIFO(mode)):
            os.close(fd)
            raise UsageError(f"--gamepad-device {path}: not a joystick device (a character "
                             "device such as /dev/input/js0)")
        if stat.S_ISCHR(mode) and not _is_joystick(fd):
            os.close(fd)
            raise UsageError(f"--gamepad-device {path}: a character device that is not a "
                             "joystick (the kernel's joystick API: /dev/input/jsN, not eventN)")
        self.fd = fd
        self.axes: dict[int, float] = {}
        self.buttons: dict[int, bool] = {}
        self.events = 0
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._read, name="jetbot-rt-gamepad",
                                        daemon=True)
        self._thread.start()

    def _read(self) -> None:
        pending = b""
        while not self._closing.is_set():
            try:
                if select.select([self.fd], [], [], POLL_S)[0]:
                    data = os.read(self.fd, EVENT.size * 64)
                    if not data:
                        self.lost(f"gamepad {self.path}: the device closed (end of file)")
                        return
                    pending += data
                    usable = len(pending) - len(pending) % EVENT.size
                    for offset in range(0, usable, EVENT.size):
                        self._event(*EVENT.unpack_from(pending, offset))
                    pending = pending[usable:]
            except BlockingIOError:
                pass
            except OSError as exc:
                if exc.errno == errno.EINTR:
                    continue
                self.lost(f"gamepad {self.path}: {exc.strerror or exc} (unplugged?)")
                return
            self._renew()

    def _event(self, _time_ms: int, value: int, kind: int, number: int) -> None:
        self.events += 1
        kind &= ~JS_EVENT_INIT
        if kind == JS_EVENT_AXIS:
            self.axes[number] = value / AXIS_FULL
        elif kind == JS_EVENT_BUTTON:
            self.buttons[number] = value != 0
            if value == 0 and number in (self.mapping.deadman_button,
                                         self.mapping.brake_button):
                self.release()  # let go: no command from this moment, not after the deadman

    def _renew(self) -> None:
        """While a button is held, the command its state gives, stamped now."""
        m = self.mapping
        if self.buttons.get(m.brake_button):
            self.propose(HandCommand((0.0, 0.0), takeover=True))
        elif self.buttons.get(m.deadman_button):
            forward = _shaped(-self.axes.get(m.forward_axis, 0.0))
            turn = _shaped(self.axes.get(m.turn_axis, 0.0))
            left = max(-1.0, min(1.0, forward + turn))
            right = max(-1.0, min(1.0, forward - turn))
            self.propose(HandCommand((left, right), takeover=True))

    def close(self) -> None:
        self._closing.set()
        if self._thread is not None:
            self._thread.join(2 * POLL_S + 0.5)
        fd, self.fd = self.fd, -1
        if fd >= 0:
            os.close(fd)
