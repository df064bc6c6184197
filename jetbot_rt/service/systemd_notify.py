"""systemd's notify protocol (``sd_notify``) in pure Python: READY, WATCHDOG, STATUS, STOPPING.

Each message is one AF_UNIX datagram of ``KEY=value`` lines sent to ``$NOTIFY_SOCKET`` (a
filesystem path, or an abstract name written with a leading ``@``). Without ``NOTIFY_SOCKET``
every method does nothing. A failed send is reported once on stderr and never raised: losing
the service manager must not stop the robot's loop, and a missed WATCHDOG=1 lets systemd act.
"""

from __future__ import annotations

import os
import socket
import sys
from collections.abc import Callable

STATUS_INTERVAL = 1.0
"""Seconds between STATUS= updates sent from the control loop."""
WATCHDOG_FRACTION = 3
"""WATCHDOG=1 goes out every WATCHDOG_USEC / 3: at least twice per timeout even with jitter."""


def _socket_address(value: str) -> str | bytes:
    # An abstract socket's name starts with a NUL byte; systemd writes it as '@'.
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    return value


def _positive_int(value: str | None) -> int | None:
    try:
        number = int(value) if value else 0
    except ValueError:
        return None
    return number if number > 0 else None


class Notifier:
    """Talks to the service manager for one process. ``tick`` runs on the control-loop thread;
    ``ready`` and ``stopping`` may run on any thread."""

    def __init__(
        self,
        address: str | None,
        watchdog_usec: int | None = None,
        watchdog_pid: int | None = None,
    ) -> None:
        self._name = address
        self._address = _socket_address(address) if address else None
        self._socket: socket.socket | None = None
        self._send_failed = False
        # As sd_watchdog_enabled(): the watchdog is ours unless WATCHDOG_PID names another process.
        mine = watchdog_pid is None or watchdog_pid == os.getpid()
        self._watchdog_usec = watchdog_usec if (address and watchdog_usec and mine) else None
        self._ready = False
        self._stopping = False
        self._next_ping: float | None = None
        self._next_status: float | None = None

    @classmethod
    def from_env(cls) -> Notifier:
        env = os.environ
        pid_text = env.get("WATCHDOG_PID")
        # An unparsable WATCHDOG_PID means "not ours", as in libsystemd.
        pid = (_positive_int(pid_text) or -1) if pid_text else None
        return cls(env.get("NOTIFY_SOCKET") or None, _positive_int(env.get("WATCHDOG_USEC")), pid)

    @property
    def enabled(self) -> bool:
        """True when there is a service manager to talk to."""
        return self._address is not None

    @property
    def watchdog_enabled(self) -> bool:
        return self._watchdog_usec is not None

    @property
    def watchdog_interval(self) -> float | None:
        """Seconds between WATCHDOG=1 messages (a third of systemd's WatchdogSec), or None."""
        if self._watchdog_usec is None:
            return None
        return self._watchdog_usec / 1e6 / WATCHDOG_FRACTION

    def ready(self, status: str) -> None:
        """The camera delivers frames and the policy is warm: the service counts as started."""
        self._ready = True
        self._send(["READY=1", _status_line(status)])

    @property
    def active(self) -> bool:
        """Whether there is a service manager to tell anything (``NOTIFY_SOCKET``)."""
        return self._address is not None

    def tick(self, now: float, status: Callable[[], str]) -> None:
        """After each completed tick, ``now`` from ``time.monotonic()``. Sends WATCHDOG=1 when
        due and a STATUS= line at most once per second; nothing before ``ready`` or after
        ``stopping``, so a loop that stops completing ticks stops feeding the watchdog."""
        if self._address is None or not self._ready or self._stopping:
            return
        lines = []
        interval = self.watchdog_interval
        if interval is not None and (self._next_ping is None or now >= self._next_ping):
            lines.append("WATCHDOG=1")
            self._next_ping = now + interval
        if self._next_status is None or now >= self._next_status:
            lines.append(_status_line(status()))
            self._next_status = now + STATUS_INTERVAL
        if lines:
            self._send(lines)

    def stopping(self, status: str) -> None:
        """The process is on its way out; no WATCHDOG=1 after this."""
        self._stopping = True
        self._send(["STOPPING=1", _status_line(status)])

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    def _send(self, lines: list[str]) -> None:
        if self._address is None:
            return
        message = "\n".join(lines).encode("utf-8", "replace")
        try:
            if self._socket is None:
                self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                # Never block the control loop on a full queue; a dropped ping is retried.
                self._socket.setblocking(False)
            self._socket.sendto(message, self._address)
        except OSError as exc:
            if not self._send_failed:
                self._send_failed = True
                print(
                    f"jetbot-rt: cannot notify systemd at {self._name}: "
                    f"{exc.strerror or exc} (further errors not shown)",
                    file=sys.stderr,
                    flush=True,
                )


def _status_line(status: str) -> str:
    # One datagram line per key: a newline inside STATUS would start a bogus key.
    return "STATUS=" + " ".join(status.split("\n"))
