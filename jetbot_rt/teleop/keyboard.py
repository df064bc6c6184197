"""``--input keyboard``: drive from the terminal on stdin (an ssh session works; no display).

A terminal reports key presses, never releases. A held key repeats (the terminal's or the ssh
client's auto-repeat: after a delay of 200-660 ms, then 25-40 times a second), so *hold to
drive* is: each key byte is a command valid for the deadman time (``DEADMAN_S``); a released
key stops sending, and its command expires within the deadman. The first press drives for the
deadman only, then the wheels wait for the auto-repeat to begin: with a long repeat delay the
robot moves in a short jerk first (set a shorter delay, e.g. ``xset r rate 200 30``, for a
smoother start). A burst of bytes arriving at once (an ssh connection that stalled) counts as
one press when it arrives, never as a longer drive.

Keys (``KEYS``): w/s or the up/down arrows forward/back, a/d or left/right turn on the spot,
q/e forward arcs, space brake (a zero command that, while a policy drives, also takes over:
hold it to stop the policy). x ends the drive (orderly, exit 0). Ctrl-C is the terminal's
SIGINT, as for ``run``: the terminal's signal keys stay on.

The terminal is put in non-canonical, no-echo mode (``termios``) and restored on exit, also
after a fault. End of file or a read error on it (the terminal or ssh session closed) is a lost
input: ``HandInput.lost``.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import signal
import sys
import termios
import threading
from typing import Any

from jetbot_rt.errors import UsageError
from jetbot_rt.teleop.hand import DEADMAN_S, HandCommand, HandInput

KEYS = {
    b"w": (1.0, 1.0), b"\x1b[A": (1.0, 1.0),
    b"s": (-0.6, -0.6), b"\x1b[B": (-0.6, -0.6),
    b"a": (-0.6, 0.6), b"\x1b[D": (-0.6, 0.6),
    b"d": (0.6, -0.6), b"\x1b[C": (0.6, -0.6),
    b"q": (0.35, 1.0), b"e": (1.0, 0.35),
    b" ": (0.0, 0.0),
}
"""Key (bytes as the terminal sends them) -> ``[left, right]`` in -1..1."""
QUIT = b"x"
POLL_S = 0.05
"""How often the reader looks whether it should end (closing takes at most this)."""


def split_keys(data: bytes) -> list[bytes]:
    """The keys in ``data``: arrow keys are three bytes (ESC [ A), others one."""
    keys = []
    i = 0
    while i < len(data):
        if data[i:i + 2] == b"\x1b[" and i + 2 < len(data):
            keys.append(data[i:i + 3])
            i += 3
        else:
            keys.append(data[i:i + 1])
            i += 1
    return keys


def _background(fd: int) -> bool:
    """Whether ``fd`` is our controlling terminal and another job is in its foreground (a
    fresh pty that is no one's controlling terminal has no foreground: not background)."""
    try:
        return os.tcgetpgrp(fd) != os.getpgrp()
    except OSError:
        return False


def _set_mode(fd: int, mode: list[Any]) -> None:
    """``tcsetattr`` with SIGTTOU blocked: moved to the background (Ctrl-Z, ``bg``) the
    drive would otherwise be stopped again by its own exit's restore, and its ``tcsetattr``
    fail with EINTR once continued; blocked, the kernel lets the change through."""
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTTOU})
    try:
        termios.tcsetattr(fd, termios.TCSANOW, mode)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


class KeyboardInput(HandInput):
    name = "keyboard"

    def __init__(self, fd: int = 0, deadman_s: float = DEADMAN_S) -> None:
        super().__init__(deadman_s)
        self.fd = fd
        if not os.isatty(fd):
            raise UsageError("--input keyboard needs a terminal on stdin (an ssh session "
                             "with a terminal: ssh -t)")
        if _background(fd):
            raise UsageError("--input keyboard: this is a background job of its terminal, "
                             "which cannot read keys (run it in the foreground)")
        self._saved: list[Any] | None = termios.tcgetattr(fd)
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self.presses = 0

    def start(self) -> None:
        assert self._saved is not None
        mode = list(self._saved)
        mode[3] &= ~(termios.ICANON | termios.ECHO)  # lflag; ISIG stays: Ctrl-C is SIGINT
        mode[6] = list(mode[6])
        mode[6][termios.VMIN], mode[6][termios.VTIME] = 0, 0
        _set_mode(self.fd, mode)
        print("keys: w/s forward/back, a/d turn, q/e arcs, space brake (hold to drive); "
              "x or Ctrl-C ends", file=sys.stderr, flush=True)
        self._thread = threading.Thread(target=self._read, name="jetbot-rt-keyboard",
                                        daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._closing.is_set():
            try:
                ready = select.select([self.fd], [], [], POLL_S)[0]
                if not ready:
                    continue
                data = os.read(self.fd, 256)
            except BlockingIOError:
                continue  # a console made the shared terminal description non-blocking
            except OSError as exc:
                if exc.errno == errno.EINTR:
                    continue
                self.lost(f"keyboard: terminal read failed ({exc.strerror or exc})")
                return
            if not data:
                self.lost("keyboard: the terminal closed (end of file)")
                return
            self._keys(data)

    def _keys(self, data: bytes) -> None:
        """The last key of a burst counts (the newest wish), once."""
        command = None
        for key in split_keys(data):
            if key == QUIT:
                self.on_quit("x pressed (keyboard)")
                return
            if key in KEYS:
                command = KEYS[key]
        if command is not None:
            self.presses += 1
            self.propose(HandCommand(command, takeover=True))

    def close(self) -> None:
        self._closing.set()
        if self._thread is not None:
            self._thread.join(2 * POLL_S + 0.5)
        if self._saved is not None:
            with contextlib.suppress(termios.error, OSError):
                _set_mode(self.fd, self._saved)
            self._saved = None
