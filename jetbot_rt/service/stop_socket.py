"""The runtime's control channel: a UNIX socket on which ``jetbot-rt stop`` asks a running
``jetbot-rt run`` to latch its safe stop.

Each runtime has its own socket, ``control-<pid>.sock`` in the runtime directory, so any
number of runtimes (simulations) can run side by side; the socket is for talking to a runtime,
not for keeping a second one out (that is the motor bus's owner lock, ``hal/ownership.py``).
``jetbot-rt stop`` asks every socket it finds; it does not depend on finding one: its hardware
stop defeats a runtime it cannot reach (``stop.py``).

Protocol: one line per connection. ``stop`` -> ``ok`` (after ``on_stop`` has run), ``ping``
-> ``pong``. The socket is mode 0600 in a directory of mode 0700 (``runtime_dir.py``: which
directory, and why a directory another user made first is never used), and the server answers
only its own user and root (``SO_PEERCRED``).

``request_stop`` asks every socket it trusts at once, non-blocking, within one deadline
(``ASK_TOTAL_S`` in all, however many sockets and whatever they do), and names what it did not
trust: another user's directory or socket, a link.

One thread serves every connection through a selector, never blocking on any one client: a
client that connects and says nothing, or sends half a line, or never reads the answer,
delays nobody else's ``stop``. Such a client is dropped after ``CLIENT_TIMEOUT_S``; beyond
``MAX_CLIENTS`` open connections the oldest is dropped to make room.
"""

from __future__ import annotations

import contextlib
import os
import selectors
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from jetbot_rt.errors import UsageError
from jetbot_rt.service.runtime_dir import SERVICE_DIR, default_dir, printable, private_dir, search

__all__ = ["SERVICE_DIR", "ControlServer", "StopReply", "default_socket_dir",
           "default_socket_path", "request_stop"]

SOCKET_GLOB = "control*.sock"
_MAX_REQUEST = 64
CLIENT_TIMEOUT_S = 1.0
"""A connection that has not sent its line within this time is closed."""
MAX_CLIENTS = 16
ASK_TOTAL_S = 1.0
"""``request_stop``'s whole wait, all sockets together: connecting, sending, the answers."""
MAX_ASKED = 64
"""Sockets asked at most; more are ignored and named (each is a file descriptor)."""
_RETRY_CONNECT_S = 0.005


def default_socket_dir() -> Path:
    """``runtime_dir.default_dir()``: $JETBOT_RT_RUNTIME_DIR, else $RUNTIME_DIRECTORY
    (systemd), else $XDG_RUNTIME_DIR/jetbot-rt, else /run/jetbot-rt for root and
    /tmp/jetbot-rt-<uid> for everyone else."""
    return default_dir()


def default_socket_path() -> Path:
    """This process's socket: ``control-<pid>.sock`` in ``default_socket_dir()``."""
    return default_socket_dir() / f"control-{os.getpid()}.sock"


def _remove_dead_sockets(directory: Path) -> None:
    """Sockets ``control-<pid>.sock`` of processes that are gone (SIGKILL leaves them)."""
    for path in directory.glob("control-*.sock"):
        pid = path.name[len("control-"):-len(".sock")]
        if not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            with contextlib.suppress(OSError):
                path.unlink()
        except OSError:
            pass  # alive, another user's


def _peer(conn: socket.socket) -> tuple[int, int]:
    """The pid and uid of the process at the other end."""
    creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    pid, uid, _gid = struct.unpack("3i", creds)
    return pid, uid


def runtime_answers(path: Path) -> bool:
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(0.5)
    try:
        probe.connect(str(path))
    except OSError:
        return False
    finally:
        probe.close()
    return True


class ControlServer:
    """Serves the control socket in a daemon thread until ``close()``."""

    def __init__(self, on_stop: Callable[[str], None], path: Path | None = None) -> None:
        self.on_stop = on_stop
        self.path = Path(path) if path is not None else default_socket_path()
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._closed = threading.Event()
        self._inode: int | None = None
        self._wake: tuple[socket.socket, socket.socket] | None = None
        """A socket pair: ``close()`` writes a byte so the selector returns at once."""

    def start(self) -> None:
        try:
            self._start()
        except OSError as exc:
            raise UsageError(
                f"cannot create the control socket {self.path}: {exc.strerror or exc}"
            ) from None

    def _start(self) -> None:
        # the /tmp fallback held by another user gives way to a private directory
        self.path = private_dir(self.path.parent) / self.path.name
        _remove_dead_sockets(self.path.parent)
        if self.path.exists() or self.path.is_symlink():
            if runtime_answers(self.path):
                raise UsageError(f"control socket {self.path} is in use by another process")
            self.path.unlink()  # left by a process that died
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old_umask = os.umask(0o177)  # the socket file is created 0600, never wider
        try:
            sock.bind(str(self.path))
        finally:
            os.umask(old_umask)
        os.chmod(self.path, 0o600)
        self._inode = self.path.stat().st_ino
        sock.listen(socket.SOMAXCONN)  # room for a burst; the server accepts at once
        sock.setblocking(False)
        self._sock = sock
        self._wake = socket.socketpair()
        for end in self._wake:
            end.setblocking(False)
        self._thread = threading.Thread(target=self._serve, name="jetbot-rt-control", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._closed.set()
        if self._wake is not None:
            with contextlib.suppress(OSError):
                self._wake[1].send(b"x")
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if self._wake is not None:
            for end in self._wake:
                end.close()
            self._wake = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
            # Remove the file only if it is still ours (not a successor's).
            with contextlib.suppress(OSError):
                if self.path.stat().st_ino == self._inode:
                    self.path.unlink()

    def _serve(self) -> None:
        assert self._sock is not None
        selector = selectors.DefaultSelector()
        selector.register(self._sock, selectors.EVENT_READ)
        assert self._wake is not None
        wake = self._wake[0]
        selector.register(wake, selectors.EVENT_READ)
        clients: dict[socket.socket, tuple[float, bytes]] = {}  # -> (connected at, bytes)
        try:
            while not self._closed.is_set():
                for key, _events in selector.select(timeout=0.1):
                    if key.fileobj is wake:
                        continue  # close(): the loop's condition ends it
                    if key.fileobj is self._sock:
                        self._accept(selector, clients)
                    else:
                        self._read(selector, clients, key.fileobj)  # type: ignore[arg-type]
                now = time.monotonic()
                for conn, (since, _) in list(clients.items()):
                    if now - since > CLIENT_TIMEOUT_S:
                        self._drop(selector, clients, conn)
        finally:
            for conn in list(clients):
                self._drop(selector, clients, conn)
            selector.close()

    def _accept(self, selector: selectors.BaseSelector,
                clients: dict[socket.socket, tuple[float, bytes]]) -> None:
        assert self._sock is not None
        try:
            conn, _ = self._sock.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            if not self._closed.is_set():
                raise
            return
        if len(clients) >= MAX_CLIENTS:  # make room: the oldest has waited longest
            oldest = min(clients, key=lambda c: clients[c][0])
            self._drop(selector, clients, oldest)
        conn.setblocking(False)
        clients[conn] = (time.monotonic(), b"")
        selector.register(conn, selectors.EVENT_READ)

    def _read(self, selector: selectors.BaseSelector,
              clients: dict[socket.socket, tuple[float, bytes]], conn: socket.socket) -> None:
        since, data = clients[conn]
        try:
            chunk = conn.recv(_MAX_REQUEST)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            chunk = b""
        data += chunk
        if chunk and b"\n" not in data and len(data) < _MAX_REQUEST:
            clients[conn] = (since, data)
            return
        with contextlib.suppress(OSError):  # a client gone, or one that does not read
            self._answer(conn, data)
        self._drop(selector, clients, conn)

    @staticmethod
    def _drop(selector: selectors.BaseSelector,
              clients: dict[socket.socket, tuple[float, bytes]], conn: socket.socket) -> None:
        clients.pop(conn, None)
        with contextlib.suppress(KeyError, ValueError):
            selector.unregister(conn)
        conn.close()

    def _answer(self, conn: socket.socket, data: bytes) -> None:
        request = data.decode(errors="replace").strip()
        pid, uid = _peer(conn)
        if uid not in (os.geteuid(), 0):  # the socket's mode already says so; twice is cheap
            reply = "error not allowed"
        elif request == "stop":
            try:
                self.on_stop(f"jetbot-rt stop from pid {pid}")
                reply = "ok"
            except Exception as exc:
                reply = f"error {type(exc).__name__}: {exc}"
        elif request == "ping":
            reply = "pong"
        else:
            reply = "error unknown request"
        # Non-blocking: an answer of a few bytes fits in the socket buffer; a client that
        # never reads cannot hold this thread.
        conn.send(reply.encode() + b"\n")


@dataclass
class StopReply:
    """What ``request_stop`` found: runtimes that latched, sockets it could not reach (a live
    runtime behind a permission error keeps driving, which the caller must say), and what it
    did not trust (never asked)."""

    acknowledged: list[Path] = field(default_factory=list)
    unreachable: list[str] = field(default_factory=list)
    ignored: list[str] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.acknowledged)


class _Ask:
    """One socket being asked: connected, ``stop`` sent, its answer arriving."""

    def __init__(self, path: Path, sock: socket.socket) -> None:
        self.path = path
        self.sock = sock
        self.answer = b""


def _connect(path: Path) -> _Ask | str | None:
    """A connected socket with ``stop`` sent; None for a stale socket (nobody listens), ""
    for a full listen queue (try again: a UNIX socket does not wait for room), else why
    not. Never blocks."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.setblocking(False)
    try:
        sock.connect(str(path))
        _pid, uid = _peer(sock)
        if uid not in (os.geteuid(), 0, os.lstat(path).st_uid):
            sock.close()
            return f"served by uid {uid}"
        sock.send(b"stop\n")
    except BlockingIOError:
        sock.close()
        return ""
    except (ConnectionRefusedError, FileNotFoundError):
        sock.close()
        return None  # stale socket of a runtime that is gone
    except OSError as exc:
        sock.close()
        return exc.strerror or str(exc)
    return _Ask(path, sock)


def _receive(ask: _Ask) -> bool:
    """Read what has arrived; True once the answer is complete (a line, or the end)."""
    try:
        chunk = ask.sock.recv(_MAX_REQUEST)
    except (BlockingIOError, InterruptedError):
        return False
    except OSError:
        chunk = b""
    ask.answer += chunk
    return not chunk or b"\n" in ask.answer or len(ask.answer) >= _MAX_REQUEST


def request_stop(path: Path | None = None, timeout: float = ASK_TOTAL_S) -> StopReply:
    """Ask running runtimes to latch their safe stop, all at once, for at most ``timeout``
    seconds in all.

    Without ``path``, every socket ``runtime_dir.search`` trusts in the runtime directories
    (at most ``MAX_ASKED``). A socket file nobody listens on (a runtime that died) is neither
    acknowledged nor unreachable.
    """
    deadline = time.monotonic() + timeout
    if path is not None:
        candidates, reply = [Path(path)], StopReply()
    else:
        found = search(SOCKET_GLOB, MAX_ASKED)
        candidates = found.sockets
        reply = StopReply(unreachable=list(found.problems), ignored=list(found.ignored))
    selector = selectors.DefaultSelector()
    to_connect = candidates
    try:
        while to_connect or selector.get_map():
            retry = []
            for candidate in to_connect:
                outcome = _connect(candidate)
                if isinstance(outcome, _Ask):
                    selector.register(outcome.sock, selectors.EVENT_READ, outcome)
                elif outcome == "":
                    retry.append(candidate)
                elif outcome is not None:
                    reply.unreachable.append(f"{printable(candidate)}: {outcome}")
            to_connect = retry
            left = deadline - time.monotonic()
            # Nothing to wait for (every socket stale or refused): a select on an empty map
            # would sit out the whole timeout, and `jetbot-rt stop` answer 1 s late.
            if left <= 0 or not (to_connect or selector.get_map()):
                break
            wait = min(left, _RETRY_CONNECT_S) if to_connect else left
            for key, _events in selector.select(wait):
                ask = key.data
                if _receive(ask):
                    selector.unregister(ask.sock)
                    ask.sock.close()
                    if ask.answer.strip() == b"ok":
                        reply.acknowledged.append(ask.path)
                    else:
                        reply.unreachable.append(
                            f"{printable(ask.path)}: unexpected answer {ask.answer[:40]!r}")
    finally:
        for key in list(selector.get_map().values()):
            key.data.sock.close()
            reply.unreachable.append(
                f"{printable(key.data.path)}: no answer within {timeout:g} s")
        selector.close()
    reply.unreachable += [f"{printable(c)}: its listen queue stayed full" for c in to_connect]
    return reply
