"""The runtime's control channel: a UNIX socket on which ``jetbot-rt stop`` asks a running
``jetbot-rt run`` to latch its safe stop.

Each runtime has its own socket, ``control-<pid>.sock`` in the runtime directory, so any
number of runtimes (simulations) can run side by side; the socket is for talking to a runtime,
not for keeping a second one out (that is the motor bus's owner lock, ``hal/ownership.py``).
``jetbot-rt stop`` asks every socket it finds; it does not depend on finding one: its hardware
stop defeats a runtime it cannot reach (``stop.py``).

Protocol: one line per connection. ``stop`` -> ``ok`` (after ``on_stop`` has run), ``ping``
-> ``pong``. The socket is mode 0600 in a directory of mode 0700, so only the runtime's user
(and root) can stop it this way.

One thread serves every connection through a selector, never blocking on any one client: a
client that connects and says nothing, or sends half a line, or never reads the answer,
delays nobody else's ``stop``. Such a client is dropped after ``CLIENT_TIMEOUT_S``; beyond
``MAX_CLIENTS`` open connections the oldest is dropped to make room.
"""

from __future__ import annotations

import contextlib
import fnmatch
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

SOCKET_GLOB = "control*.sock"
# The systemd unit's RuntimeDirectory=jetbot-rt: where the service's socket is, seen from a
# shell that has no $RUNTIME_DIRECTORY.
SERVICE_DIR = Path("/run/jetbot-rt")
_MAX_REQUEST = 64
CLIENT_TIMEOUT_S = 1.0
"""A connection that has not sent its line within this time is closed."""
MAX_CLIENTS = 16


def default_socket_dir() -> Path:
    """$JETBOT_RT_RUNTIME_DIR, else $RUNTIME_DIRECTORY (systemd), else
    $XDG_RUNTIME_DIR/jetbot-rt, else /tmp/jetbot-rt-<uid>."""
    explicit = os.environ.get("JETBOT_RT_RUNTIME_DIR")
    if explicit:
        return Path(explicit)
    systemd = os.environ.get("RUNTIME_DIRECTORY")
    if systemd:
        return Path(systemd.split(":")[0])  # systemd joins several with ':'
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg:
        return Path(xdg) / "jetbot-rt"
    return Path(f"/tmp/jetbot-rt-{os.getuid()}")


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


def _peer_pid(conn: socket.socket) -> int:
    creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return struct.unpack("3i", creds)[0]


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


def _private_dir(directory: Path) -> None:
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    if directory.stat().st_uid != os.getuid():
        raise UsageError(f"control socket directory {directory} belongs to another user")


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
        _private_dir(self.path.parent)
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
        if request == "stop":
            try:
                self.on_stop(f"jetbot-rt stop from pid {_peer_pid(conn)}")
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


def _candidates(path: Path | None) -> tuple[list[Path], list[str]]:
    """The sockets to ask, and the directories that could not be listed."""
    if path is not None:
        return [Path(path)], []
    directories = [default_socket_dir()]
    explicit = os.environ.get("JETBOT_RT_RUNTIME_DIR") or os.environ.get("RUNTIME_DIRECTORY")
    if not explicit and SERVICE_DIR not in directories:
        directories.append(SERVICE_DIR)
    paths: list[Path] = []
    problems: list[str] = []
    for directory in directories:
        try:
            names = sorted(os.listdir(directory))
        except FileNotFoundError:
            continue
        except OSError as exc:  # the service's directory, seen by another user
            problems.append(f"{directory}: {exc.strerror or exc}")
            continue
        paths += [directory / n for n in names if fnmatch.fnmatch(n, SOCKET_GLOB)]
    return paths, problems


@dataclass
class StopReply:
    """What ``request_stop`` found: runtimes that latched, and sockets it could not reach
    (a live runtime behind a permission error keeps driving, which the caller must say)."""

    acknowledged: list[Path] = field(default_factory=list)
    unreachable: list[str] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.acknowledged)


def _connect(client: socket.socket, path: Path, timeout: float) -> None:
    """Connect, retrying while the listen queue is full (EAGAIN: a UNIX socket does not wait
    for room, even with a timeout): a flood of other clients must not turn a stop away."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            client.connect(str(path))
            return
        except BlockingIOError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.005)


def request_stop(path: Path | None = None, timeout: float = 0.5) -> StopReply:
    """Ask a running runtime to latch its safe stop.

    Without ``path``, tries every socket in the default directory, then (unless a runtime
    directory is set in the environment) in the systemd service's. A socket file nobody
    listens on (a runtime that died) is neither acknowledged nor unreachable.
    """
    candidates, problems = _candidates(path)
    reply = StopReply(unreachable=problems)
    for candidate in candidates:
        if not candidate.exists():
            continue
        client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        client.settimeout(timeout)
        try:
            _connect(client, candidate, timeout)
            client.sendall(b"stop\n")
            answer = client.recv(_MAX_REQUEST)
        except (ConnectionRefusedError, FileNotFoundError):
            continue  # stale socket of a runtime that is gone
        except OSError as exc:
            reply.unreachable.append(f"{candidate}: {exc.strerror or exc}")
            continue
        finally:
            client.close()
        if answer.strip() == b"ok":
            reply.acknowledged.append(candidate)
        else:
            reply.unreachable.append(f"{candidate}: unexpected answer {answer[:40]!r}")
    return reply
