"""The monitor's HTTP server: the standard library's ``ThreadingHTTPServer`` in threads of its
own, read-only but for one thing, ``POST /stop``, which trips the same latch as ``jetbot-rt
stop``.

Routes: ``GET /`` (the page), ``/monitor.js``, ``/monitor.css`` (static files shipped in the
package, read once at start), ``GET /state`` (one JSON object), ``GET /frame.jpg?view=`` (the
newest frame, ``prepared`` or ``raw``), ``GET /stream.mjpg?view=`` (MJPEG, the page's live
image), ``GET /events`` (server-sent events: the state at up to ``max_fps``, then the end),
``POST /stop``; ``POST /drive`` only under ``jetbot-rt drive --input page`` with ``[monitor]
drive = true``. Nothing else: no file is served by name, nothing is written, no CORS header.

Why MJPEG and server-sent events: both are plain HTTP responses an ``<img>`` and an
``EventSource`` read with no code of ours, each frame or state replaces the last (a late one
is simply skipped), and both are a few lines on the server; a WebSocket needs a handshake and
framing the standard library lacks, for a channel that only ever flows one way.

Bounds (a flood of clients costs the page, never a tick or a stop: the loop does not wait on
anything here, and ``jetbot-rt stop`` and signals do not go through here):
- ``MAX_CONNECTIONS`` open at once; at the limit a new one evicts the oldest that has not
  finished sending its request, and beyond that is closed unanswered.
- a request (line and headers) within ``MAX_REQUEST_BYTES`` and ``REQUEST_TIMEOUT_S`` in all
  (a reaper closes slower ones: one byte a second does not keep a thread); a POST's body
  within the same bound.
- ``MAX_STREAMS`` streams at once (503 beyond); a stream write that waits longer than
  ``SEND_TIMEOUT_S`` (a client that never reads) ends that stream.
- HTTP/1.0: one request per connection.

Access: on a loopback address the ``Host`` header must name a loopback host (a web page that
rebinds its own name to 127.0.0.1 is refused). On any other address every request needs the
token: ``Authorization: Bearer TOKEN`` or the cookie that ``GET /?token=TOKEN`` sets (then
redirected to ``/``, so the token leaves the address bar); compared in constant time; 403 and
nothing else otherwise.
"""

from __future__ import annotations

import contextlib
import http.cookies
import json
import math
import pkgutil
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Callable
from urllib.parse import parse_qs, urlsplit

from jetbot_rt.monitor import token as tokens
from jetbot_rt.monitor.config import Listen
from jetbot_rt.monitor.observer import VIEWS, RunView

MAX_CONNECTIONS = 32
MAX_STREAMS = 16
"""Five pages (each: two MJPEG images and the event stream) and a script."""
MAX_REQUEST_BYTES = 8 * 1024
REQUEST_TIMEOUT_S = 5.0
SEND_TIMEOUT_S = 5.0
END_LINGER_S = 1.0
"""How long the server waits at the end for its streams to send the final state."""
COOKIE = "jetbot_rt_monitor"
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
STATIC = {"/": ("index.html", "text/html; charset=utf-8"),
          "/monitor.js": ("monitor.js", "text/javascript; charset=utf-8"),
          "/monitor.css": ("monitor.css", "text/css; charset=utf-8")}
SECURITY_HEADERS = (
    ("Cache-Control", "no-store"),
    ("X-Content-Type-Options", "nosniff"),
    ("Referrer-Policy", "no-referrer"),
    ("X-Frame-Options", "DENY"),
    ("Content-Security-Policy", "default-src 'self'; img-src 'self'; frame-ancestors 'none'; "
                                "form-action 'none'; base-uri 'none'"),
)


class RequestTooLarge(Exception):
    pass


class _BoundedReader:
    """The request's reader: at most ``limit`` bytes in all (headers included)."""

    def __init__(self, raw: Any, limit: int) -> None:
        self.raw = raw
        self.left = limit

    def readline(self, size: int = -1) -> bytes:
        if self.left <= 0:
            raise RequestTooLarge
        want = self.left + 1 if size < 0 else min(size, self.left + 1)
        line = self.raw.readline(want)
        self.left -= len(line)
        if self.left < 0:
            raise RequestTooLarge
        return bytes(line)

    def read(self, size: int) -> bytes:
        if size > self.left:
            raise RequestTooLarge
        data = bytes(self.raw.read(size))
        self.left -= len(data)
        return data

    def close(self) -> None:
        self.raw.close()


def finite(value: Any) -> Any:
    """JSON a browser parses: NaN and infinities as null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    return value


def _static(name: str) -> bytes:
    data = pkgutil.get_data("jetbot_rt.monitor", f"static/{name}")
    assert data is not None, name  # shipped in the package (pyproject's package data)
    return data


class MonitorServer(ThreadingHTTPServer):
    daemon_threads = True
    request_queue_size = 64

    def __init__(self, listen: Listen, view: RunView, on_stop: Callable[[str], None],
                 token: str | None, max_fps: float = 15.0) -> None:
        self.address_family = socket.AF_INET6 if ":" in listen.host else socket.AF_INET
        self.view = view
        self.on_stop = on_stop
        self.on_drive: Callable[[float, float], None] | None = None
        """``jetbot-rt drive --input page`` sets it: ``POST /drive`` exists only then."""
        self.token = token
        self.loopback = listen.loopback
        self.interval = 1.0 / max_fps
        self.files = {path: (_static(name), kind) for path, (name, kind) in STATIC.items()}
        self.closing = threading.Event()
        self.counts = {"clients": 0, "streams": 0, "frames_sent": 0, "frames_dropped": 0,
                       "refused": 0, "forbidden": 0}
        self._lock = threading.Lock()
        self._reading: dict[socket.socket, float] = {}
        self._open = 0
        self._thread: threading.Thread | None = None
        # bind now (a port in use is refused before the robot connects); serve in start()
        super().__init__((listen.host, listen.port), MonitorHandler)

    # ---- admission -------------------------------------------------------------------------

    def process_request(self, request: Any, client_address: Any) -> None:
        with self._lock:
            # At the limit the oldest connection still sending its request makes room (its
            # thread ends at once); with none such, the new one is closed unanswered.
            if self._open >= MAX_CONNECTIONS and not self._evict_oldest_reading():
                self.counts["refused"] += 1
                self.shutdown_request(request)
                return
            self._open += 1
            self.counts["clients"] = self._open
            self._reading[request] = time.monotonic()
        try:
            super().process_request(request, client_address)
        except Exception:  # a thread that cannot start: drop this connection, keep serving
            self._closed(request)
            self.shutdown_request(request)

    def _evict_oldest_reading(self) -> bool:
        if not self._reading:
            return False
        oldest = min(self._reading, key=self._reading.__getitem__)
        del self._reading[oldest]
        self.counts["refused"] += 1
        _shut(oldest)
        return True

    def request_read(self, request: Any) -> None:
        with self._lock:
            self._reading.pop(request, None)

    def _closed(self, request: Any) -> None:
        with self._lock:
            self._reading.pop(request, None)
            self._open -= 1
            self.counts["clients"] = self._open

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._closed(request)

    def service_actions(self) -> None:
        """Between two polls of the accept loop: requests slower than the limit are closed,
        the view samples its rate and path."""
        deadline = time.monotonic() - REQUEST_TIMEOUT_S
        with self._lock:
            slow = [r for r, t in self._reading.items() if t < deadline]
            for request in slow:
                del self._reading[request]
        for request in slow:
            _shut(request)
        self.view.sample()

    def handle_error(self, request: Any, client_address: Any) -> None:
        pass  # a client's broken connection is the client's; nothing to print on the journal

    # ---- streams ---------------------------------------------------------------------------

    def open_stream(self) -> bool:
        with self._lock:
            if self.counts["streams"] >= MAX_STREAMS or self.closing.is_set():
                return False
            self.counts["streams"] += 1
            return True

    def close_stream(self) -> None:
        with self._lock:
            self.counts["streams"] -= 1

    def count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counts[key] += n

    # ---- life ------------------------------------------------------------------------------

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{port}/"

    def start(self) -> None:
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="jetbot-rt-monitor", daemon=True)
        self._thread.start()

    def close(self, linger: float = END_LINGER_S) -> None:
        """Stop accepting; give the streams ``linger`` s to send the end; close. Bounded."""
        self.closing.set()
        deadline = time.monotonic() + linger
        while time.monotonic() < deadline and self.counts["streams"] > 0:
            time.sleep(0.02)
        if self._thread is not None:
            self.shutdown()
            self._thread.join(1.0)
        self.server_close()


def _shut(request: socket.socket) -> None:
    with contextlib.suppress(OSError):
        request.shutdown(socket.SHUT_RDWR)  # wakes the thread blocked in recv on it


class MonitorHandler(BaseHTTPRequestHandler):
    server: MonitorServer
    protocol_version = "HTTP/1.0"
    server_version = "jetbot-rt-monitor"
    sys_version = ""
    timeout = REQUEST_TIMEOUT_S

    def setup(self) -> None:
        super().setup()
        self.rfile = _BoundedReader(self.rfile, MAX_REQUEST_BYTES)  # type: ignore[assignment]

    def handle(self) -> None:
        try:
            self.handle_one_request()
        except RequestTooLarge:
            self.close_connection = True
            self._send(HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE, b"request too large\n")
        except (OSError, ValueError):
            self.close_connection = True  # the client went away or sent garbage

    def parse_request(self) -> bool:
        ok = super().parse_request()
        self.server.request_read(self.request)
        self.connection.settimeout(SEND_TIMEOUT_S)
        return ok

    def log_message(self, format: str, *args: Any) -> None:
        pass  # requests are not journal material; the counts are in /state

    # ---- access ----------------------------------------------------------------------------

    def _allowed(self, query_token: str | None = None) -> bool:
        server = self.server
        if server.token is None:
            return self._loopback_host()
        given: str | None = query_token
        auth = self.headers.get("Authorization", "")
        if given is None and auth.startswith("Bearer "):
            given = auth[len("Bearer "):].strip()
        if given is None:
            cookie = http.cookies.SimpleCookie()
            try:
                cookie.load(self.headers.get("Cookie", ""))
            except http.cookies.CookieError:
                return False
            if COOKIE in cookie:
                given = cookie[COOKIE].value
        return tokens.matches(given, server.token)

    def _loopback_host(self) -> bool:
        """On a loopback bind the Host must be a loopback name: a page on another site that
        made its own name resolve to 127.0.0.1 (DNS rebinding) is refused."""
        host = self.headers.get("Host", "")
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        if host.startswith("["):
            name = host[1:].split("]", 1)[0]
        return name in LOOPBACK_NAMES

    def _own_user(self) -> bool:
        from jetbot_rt.monitor.peer import peer_uid, trusted_uids

        uid = peer_uid(self.server.address_family, self.client_address,
                       self.connection.getsockname())
        return uid is not None and uid in trusted_uids()

    def _forbid(self) -> None:
        self.server.count("forbidden")
        self._send(HTTPStatus.FORBIDDEN, b"forbidden\n")

    # ---- responses -------------------------------------------------------------------------

    def _headers(self, status: int, kind: str, length: int | None = None,
                 extra: tuple[tuple[str, str], ...] = ()) -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        if length is not None:
            self.send_header("Content-Length", str(length))
        for name, value in SECURITY_HEADERS + extra:
            self.send_header(name, value)
        self.end_headers()

    def _send(self, status: int, body: bytes, kind: str = "text/plain; charset=utf-8",
              extra: tuple[tuple[str, str], ...] = ()) -> None:
        try:
            self._headers(status, kind, len(body), extra)
            self.wfile.write(body)
        except OSError:
            pass

    def _json(self, value: Any) -> bytes:
        return json.dumps(finite(value), separators=(",", ":")).encode()

    def _view(self, query: dict[str, list[str]]) -> str | None:
        view = query.get("view", ["prepared"])[0]
        return view if view in VIEWS else None

    # ---- routes ----------------------------------------------------------------------------

    def do_GET(self) -> None:
        url = urlsplit(self.path)
        query = parse_qs(url.query, max_num_fields=4)
        if url.path == "/" and "token" in query and self.server.token is not None:
            return self._token_login(query["token"][0])
        if not self._allowed():
            return self._forbid()
        server = self.server
        if url.path in server.files:
            body, kind = server.files[url.path]
            return self._send(HTTPStatus.OK, body, kind)
        if url.path == "/state":
            state = server.view.state(server.counts)
            state["drive"] = server.on_drive is not None
            return self._send(HTTPStatus.OK, self._json(state), "application/json")
        view = self._view(query)
        if url.path == "/frame.jpg" and view is not None:
            frame = server.view.jpeg(view)
            if frame is None:
                return self._send(HTTPStatus.SERVICE_UNAVAILABLE, b"no frame yet\n")
            return self._send(HTTPStatus.OK, frame[1], "image/jpeg",
                              (("X-Tick", str(frame[0])),))
        if url.path == "/stream.mjpg" and view is not None:
            return self._stream(lambda: self._mjpeg(view))
        if url.path == "/events":
            return self._stream(self._events)
        self._send(HTTPStatus.NOT_FOUND, b"not found\n")

    def do_POST(self) -> None:
        # a body (none is needed) is read within the request's bound, so that closing the
        # connection does not reset it before the client has the answer
        length = self.headers.get("Content-Length", "0").strip()
        body = self.rfile.read(int(length) if length.isdigit() else MAX_REQUEST_BYTES + 1)
        if not self._allowed():
            return self._forbid()
        path = urlsplit(self.path).path
        on_drive = self.server.on_drive  # once: the drive's stop clears it from its thread
        if path not in ("/stop", "/drive") or (path == "/drive" and on_drive is None):
            return self._send(HTTPStatus.NOT_FOUND, b"not found\n")
        origin = self.headers.get("Origin")
        if origin is not None and urlsplit(origin).netloc != self.headers.get("Host"):
            return self._forbid()  # a form on another site; the page's own POST passes
        if path == "/drive":
            if self.server.token is None and not self._own_user():
                return self._forbid()  # no token on loopback: another local account
            assert on_drive is not None  # the local read once above: no race
            return self._drive(body, on_drive)
        peer = self.client_address[0]
        self.server.on_stop(f"stop from the monitor page ({peer})")
        self._send(HTTPStatus.OK, b"stopping\n")

    def _drive(self, body: bytes, on_drive: Callable[[float, float], None]) -> None:
        """``{"left": L, "right": R}``, each a number in -1..1: a hand command for the deadman
        time (the page repeats it while a button is held). Anything else: 400, nothing moves."""
        try:
            command = json.loads(body.decode("utf-8")) if len(body) <= 256 else None
            given = [command[key] for key in ("left", "right")]
            if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in given):
                raise TypeError  # true, "1": not a number, though float() takes them
            left, right = (float(v) for v in given)
            if not (-1.0 <= left <= 1.0 and -1.0 <= right <= 1.0):
                raise ValueError
        except (ValueError, TypeError, KeyError, UnicodeDecodeError):
            return self._send(HTTPStatus.BAD_REQUEST,
                              b'{"left": L, "right": R} with L, R in -1..1\n')
        on_drive(left, right)
        self._send(HTTPStatus.OK, b"ok\n")

    def _token_login(self, given: str) -> None:
        if not tokens.matches(given, self.server.token or ""):
            return self._forbid()
        cookie = f"{COOKIE}={given}; Path=/; HttpOnly; SameSite=Strict"
        self._send(HTTPStatus.SEE_OTHER, b"", extra=(("Location", "/"), ("Set-Cookie", cookie)))

    # ---- streams ---------------------------------------------------------------------------

    def _stream(self, body: Callable[[], None]) -> None:
        server = self.server
        if not server.open_stream():
            return self._send(HTTPStatus.SERVICE_UNAVAILABLE, b"too many streams\n")
        try:
            body()
        except OSError:
            pass  # the client left or stopped reading for SEND_TIMEOUT_S
        finally:
            server.close_stream()

    def _paced(self) -> Any:
        """Yields once per ``interval`` while serving; counts the slots a slow client missed
        (a write took longer than the interval, or timed out) as dropped frames."""
        server = self.server
        interval = server.interval
        next_at = time.monotonic()
        try:
            while not server.closing.is_set():
                yield
                next_at += interval
                now = time.monotonic()
                if now > next_at:
                    missed = int((now - next_at) // interval) + 1
                    server.count("frames_dropped", missed)
                    next_at += missed * interval
                server.closing.wait(max(0.0, next_at - time.monotonic()))
        finally:  # also a write that timed out: the slots it sat through are dropped
            late = time.monotonic() - next_at
            if late > interval:
                server.count("frames_dropped", int(late // interval))

    def _mjpeg(self, view: str) -> None:
        boundary = "jetbotrtframe"
        self._headers(HTTPStatus.OK, f"multipart/x-mixed-replace; boundary={boundary}")
        sent_tick = -1
        for _ in self._paced():
            frame = self.server.view.jpeg(view)
            if frame is None or frame[0] == sent_tick:
                continue
            sent_tick, data = frame
            self.wfile.write(b"--%s\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                             % (boundary.encode(), len(data)) + data + b"\r\n")
            self.server.count("frames_sent")

    def _events(self) -> None:
        server = self.server
        self._headers(HTTPStatus.OK, "text/event-stream")
        last = b""
        for n, _ in enumerate(self._paced()):
            # the sim's path (up to thousands of points) once a second, the rest each time
            with_path = n % max(1, round(1.0 / server.interval)) == 0
            data = self._json(server.view.state(server.counts, trajectory=with_path))
            if data != last:
                self.wfile.write(b"data: " + data + b"\n\n")
                last = data
            if server.view.ended is not None:
                # the end is always sent below, read after the check: the run can end
                # between the state written above and this check
                break
        data = self._json(server.view.state(server.counts))
        self.wfile.write(b"event: end\ndata: " + data + b"\n\n")
