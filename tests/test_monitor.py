"""The monitor's server over real sockets: the API, the token rules, and clients that try to
hold it up (never reading, 100 connections, huge headers, slow requests, stops without the
token). A synthetic tick feeder stands in for the loop (the real loop: test_monitor_run)."""

from __future__ import annotations

import http.client
import json
import os
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from jetbot_rt.errors import UsageError
from jetbot_rt.monitor import server as monitor_server
from jetbot_rt.monitor import start
from jetbot_rt.monitor import token as tokens
from jetbot_rt.monitor.config import MonitorConfig, parse_listen
from jetbot_rt.monitor.observer import RunView
from jetbot_rt.runtime.loop import LoopStats, TickResult
from jetbot_rt.runtime.safety import SafeStopLatch

BIG = (480, 640, 3)  # noise this size is a JPEG of ~200 KB: a stalled client's buffers fill


@dataclass
class Served:
    server: monitor_server.MonitorServer
    latch: SafeStopLatch
    port: int
    stop_feed: threading.Event
    said: list[str]

    def request(self, method: str, path: str, headers: dict[str, str] | None = None,
                ) -> tuple[int, dict[str, str], bytes]:
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
        try:
            conn.request(method, path, headers=headers or {})
            reply = conn.getresponse()
            return reply.status, dict(reply.getheaders()), reply.read()
        finally:
            conn.close()


def feed(view: RunView, stats: LoopStats, stop: threading.Event, shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, shape, dtype=np.uint8) for _ in range(4)]
    while not stop.is_set():
        stats.ticks += 1
        now = time.monotonic()
        view.observe(TickResult(
            tick=stats.ticks, t_start=now, deadline=now, image=images[stats.ticks % 4],
            frame_index=stats.ticks, frame_age_ms=3.0, mu=[0.5, -0.25], cmd=(0.05, -0.025),
            infer_ms=1.0, tick_ms=2.0, write_ms=0.3, advance_ms=None, overruns=0,
            extra={"pose": [stats.ticks * 0.01, 0.0, 0.0]}))
        stop.wait(0.02)


def serve(listen: str, token_file: str | None = None, shape: tuple[int, ...] = (96, 128, 3),
          ) -> Iterator[Served]:
    latch, stats = SafeStopLatch(), LoopStats()
    view = RunView(latch, stats, 50.0, time.monotonic(),
                   fit=lambda im: cv2.resize(im, (32, 24), interpolation=cv2.INTER_AREA))
    lines: list[str] = []
    server = start(MonitorConfig(listen=listen, token_file=token_file), view,
                   lambda reason: latch.trip(reason, fault=False), say=lines.append)
    stop = threading.Event()
    feeder = threading.Thread(target=feed, args=(view, stats, stop, shape), daemon=True)
    feeder.start()
    try:
        yield Served(server, latch, server.server_address[1], stop, lines)
    finally:
        stop.set()
        view.ended = {"reason": latch.reason, "fault": False, "exit_code": 0}
        server.close(linger=0.2)
        feeder.join()


@pytest.fixture
def local() -> Iterator[Served]:
    yield from serve("127.0.0.1:0")


@pytest.fixture
def local_big() -> Iterator[Served]:
    yield from serve("127.0.0.1:0", shape=BIG)


@pytest.fixture
def open_bind(tmp_path) -> Iterator[Served]:
    yield from serve("0.0.0.0:0", token_file=str(tmp_path / "token"))


def read_token(tmp_path) -> str:
    return (tmp_path / "token").read_text().strip()


def test_the_page_the_state_the_frames_and_the_streams_answer_on_loopback(local) -> None:
    status, headers, body = local.request("GET", "/")
    assert status == 200 and b"STOP" in body and b"/monitor.js" in body
    assert "Access-Control-Allow-Origin" not in headers
    assert "default-src 'self'" in headers["Content-Security-Policy"]
    assert local.request("GET", "/monitor.js")[0] == 200
    time.sleep(0.1)
    status, _, body = local.request("GET", "/state")
    state = json.loads(body)
    assert status == 200 and state["state"] == "driving"
    assert state["record"]["mu"] == [0.5, -0.25] and state["record"]["cmd"] == [0.05, -0.025]
    for view, shape in (("prepared", (24, 32, 3)), ("raw", (96, 128, 3))):
        status, headers, body = local.request("GET", f"/frame.jpg?view={view}")
        assert status == 200 and headers["Content-Type"] == "image/jpeg"
        image = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == shape
    assert local.request("GET", "/frame.jpg?view=../../etc/passwd")[0] == 404
    assert local.request("GET", "/nothing")[0] == 404
    assert local.request("PUT", "/stop")[0] == 501
    assert local.request("OPTIONS", "/stop")[0] == 501  # no CORS preflight answered

    conn = socket.create_connection(("127.0.0.1", local.port), timeout=10)
    conn.sendall(b"GET /stream.mjpg?view=raw HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
    data = b""
    while data.count(b"--jetbotrtframe") < 3:
        data += conn.recv(65536)
    assert b"multipart/x-mixed-replace" in data and b"Content-Type: image/jpeg" in data
    conn.close()

    conn = socket.create_connection(("127.0.0.1", local.port), timeout=10)
    conn.sendall(b"GET /events HTTP/1.0\r\nHost: localhost:9\r\n\r\n")
    data = b""
    while data.count(b"data: ") < 2:
        data += conn.recv(65536)
    first, second = (json.loads(part.split(b"\n\n")[0]) for part in data.split(b"data: ")[1:3])
    assert first["state"] == "driving" and first["trajectory"]  # the path once a second
    assert "trajectory" not in second
    conn.close()


def test_stop_is_a_post_and_latches_an_orderly_stop(local) -> None:
    assert local.request("GET", "/stop")[0] == 404
    assert not local.latch.tripped
    status, _, _ = local.request("POST", "/stop")
    assert status == 200
    assert local.latch.tripped and not local.latch.fault
    assert local.latch.reason == "stop from the monitor page (127.0.0.1)"
    assert json.loads(local.request("GET", "/state")[2])["state"] == "stopping"


def test_a_stop_posted_by_another_site_is_refused(local) -> None:
    status, _, _ = local.request("POST", "/stop", {"Origin": "http://evil.example"})
    assert status == 403 and not local.latch.tripped


def test_a_page_that_rebinds_its_name_to_loopback_is_refused(local) -> None:
    status, _, body = local.request("GET", "/state", {"Host": "evil.example:8080"})
    assert status == 403 and body == b"forbidden\n"
    assert local.request("POST", "/stop", {"Host": "evil.example"})[0] == 403
    assert not local.latch.tripped


def test_a_non_loopback_bind_needs_the_token_on_every_request(open_bind, tmp_path) -> None:
    token = read_token(tmp_path)
    assert os.stat(tmp_path / "token").st_mode & 0o777 == 0o600
    (printed,) = [line for line in open_bind.said if token in line]  # said once
    assert f"http://<this machine>:{open_bind.port}/?token={token}" in printed
    for path in ("/", "/state", "/frame.jpg", "/stream.mjpg", "/events", "/monitor.js"):
        status, headers, body = open_bind.request("GET", path)
        assert (status, body) == (403, b"forbidden\n"), path
    assert open_bind.request("GET", "/state", {"Authorization": "Bearer " + "x" * 43})[0] == 403
    assert open_bind.request("GET", "/state", {"Authorization": "Bearer " + token})[0] == 200
    assert open_bind.request("GET", "/?token=wrong")[0] == 403
    status, headers, _ = open_bind.request("GET", f"/?token={token}")
    assert status == 303 and headers["Location"] == "/"
    cookie = headers["Set-Cookie"].split(";")[0]
    assert "HttpOnly" in headers["Set-Cookie"] and "SameSite=Strict" in headers["Set-Cookie"]
    assert open_bind.request("GET", "/state", {"Cookie": cookie})[0] == 200
    assert open_bind.request("GET", "/state", {"Cookie": cookie + "x"})[0] == 403


def test_a_stop_without_or_with_a_wrong_token_does_nothing(open_bind, tmp_path) -> None:
    assert open_bind.request("POST", "/stop")[0] == 403
    assert open_bind.request("POST", "/stop", {"Authorization": "Bearer wrong"})[0] == 403
    assert open_bind.request("POST", "/stop?token=" + read_token(tmp_path))[0] == 403
    assert not open_bind.latch.tripped
    headers = {"Authorization": "Bearer " + read_token(tmp_path)}
    assert open_bind.request("POST", "/stop", headers)[0] == 200
    assert open_bind.latch.tripped and not open_bind.latch.fault


def test_the_token_file_is_reused_and_must_be_private(tmp_path) -> None:
    path = tmp_path / "token"
    token, new = tokens.load_or_create(str(path))
    assert new and tokens.load_or_create(str(path)) == (token, False)
    path.chmod(0o640)
    with pytest.raises(UsageError, match="mode 0640: others may read it"):
        tokens.load_or_create(str(path))
    path.chmod(0o600)
    link = tmp_path / "link"
    link.symlink_to(path)
    with pytest.raises(UsageError, match="symbolic link"):
        tokens.load_or_create(str(link))
    path.write_text("short\n")
    with pytest.raises(UsageError, match="at least 16 characters"):
        tokens.load_or_create(str(path))
    token, new = tokens.load_or_create(None)
    assert new and len(token) >= 32


def test_listen_addresses_are_ip_literals_with_a_port() -> None:
    assert parse_listen("8080") == ("127.0.0.1", 8080)
    assert parse_listen("localhost:80") == ("127.0.0.1", 80)
    assert parse_listen("[::1]:81").loopback
    assert not parse_listen("0.0.0.0:82").loopback
    for bad in ("example.com:80", "99999", "::1:80", "1.2.3.4:", "1.2.3.4:http", ""):
        with pytest.raises(ValueError, match=r"\[HOST:\]PORT"):
            parse_listen(bad)


def test_a_client_that_never_reads_gets_fewer_frames_and_is_dropped(local_big, monkeypatch):
    monkeypatch.setattr(monitor_server, "SEND_TIMEOUT_S", 0.5)
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled.connect(("127.0.0.1", local_big.port))
    stalled.sendall(b"GET /stream.mjpg?view=raw HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
    counts = local_big.server.counts
    deadline = time.monotonic() + 20
    while counts["frames_dropped"] == 0 and time.monotonic() < deadline:
        assert local_big.request("GET", "/state")[0] == 200  # others are served meanwhile
        time.sleep(0.05)
    assert counts["frames_dropped"] > 0
    while counts["streams"] > 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert counts["streams"] == 0  # the stream ended after SEND_TIMEOUT_S without progress
    stalled.close()


def test_a_hundred_silent_connections_do_not_keep_out_a_stop(local) -> None:
    silent = [socket.create_connection(("127.0.0.1", local.port), timeout=10)
              for _ in range(100)]
    try:
        time.sleep(0.3)
        assert local.server.counts["clients"] <= monitor_server.MAX_CONNECTIONS + 1
        status, _, _ = local.request("POST", "/stop")
        assert status == 200 and local.latch.tripped
    finally:
        for conn in silent:
            conn.close()


def test_huge_headers_are_refused_and_the_server_goes_on(local) -> None:
    conn = socket.create_connection(("127.0.0.1", local.port), timeout=10)
    try:
        conn.sendall(b"GET /state HTTP/1.0\r\nHost: 127.0.0.1\r\n")
        conn.sendall(b"X-Big: " + b"a" * 100_000 + b"\r\n\r\n")
    except OSError:
        pass  # the server closed its end before reading it all
    reply = b""
    try:
        while chunk := conn.recv(65536):
            reply += chunk
    except OSError:
        pass
    conn.close()
    assert reply == b"" or reply.startswith(b"HTTP/1.0 431")
    assert b"mu" not in reply
    assert local.request("GET", "/state")[0] == 200


def test_a_request_sent_a_byte_at_a_time_is_closed_at_the_limit(local, monkeypatch) -> None:
    monkeypatch.setattr(monitor_server, "REQUEST_TIMEOUT_S", 0.5)
    conn = socket.create_connection(("127.0.0.1", local.port), timeout=10)
    conn.sendall(b"GET /state HTTP/1.0\r\nHost: 127.0.0.1\r\nX-Slow: ")
    conn.setblocking(False)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 10:  # bound only: the server closes it long before
        try:
            if conn.recv(100) == b"":
                break  # closed by the server, unanswered
        except BlockingIOError:
            pass
        except ConnectionResetError:
            break
        try:
            conn.send(b"a")
        except OSError:
            break
        time.sleep(0.1)
    else:
        raise AssertionError("a request one byte at a time kept its connection for 10 s")
    conn.close()
    assert local.request("GET", "/state")[0] == 200


def test_a_port_in_use_is_refused_at_start() -> None:
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        with pytest.raises(UsageError, match="cannot listen: the port is in use"):
            start(MonitorConfig(listen=f"127.0.0.1:{taken.getsockname()[1]}"),
                  RunView(SafeStopLatch(), LoopStats(), 30.0, 0.0), lambda _r: None,
                  say=lambda _line: None)
    finally:
        taken.close()


def test_a_stop_with_a_body_is_answered_and_a_large_body_refused(local) -> None:
    conn = http.client.HTTPConnection("127.0.0.1", local.port, timeout=10)
    conn.request("POST", "/stop", body=b"x" * 20_000)
    reply = conn.getresponse()
    assert reply.status == 431 and not local.latch.tripped
    conn.close()
    conn = http.client.HTTPConnection("127.0.0.1", local.port, timeout=10)
    conn.request("POST", "/stop", body=b"please")
    assert conn.getresponse().status == 200 and local.latch.tripped
    conn.close()


def test_a_run_that_ends_between_a_state_and_its_check_still_tells_the_page(
        local, monkeypatch) -> None:
    view = local.server.view
    state = view.state

    def then_ends(*args, **kwargs):
        out = state(*args, **kwargs)  # read before the end: the page would not see it
        view.ended = {"reason": "a fault", "fault": True, "exit_code": 3}
        return out

    monkeypatch.setattr(view, "state", then_ends)
    conn = socket.create_connection(("127.0.0.1", local.port), timeout=10)
    conn.sendall(b"GET /events HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
    data = b""
    while chunk := conn.recv(65536):
        data += chunk
    conn.close()
    assert b"event: end" in data
    last = json.loads(data.split(b"data: ")[-1].split(b"\n\n")[0])
    assert last["ended"] == {"reason": "a fault", "fault": True, "exit_code": 3}
