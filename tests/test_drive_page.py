"""``jetbot-rt drive --input page`` on the real backend (PCA9685 emulator, videotestsrc) through
the monitor's HTTP API on a real socket: only with ``[monitor] drive = true``, a POST moves the
wheels for the deadman, a GET never does, a malformed command is refused, and when the page
stops sending the wheels are zero again."""

from __future__ import annotations

import http.client
import json
import subprocess
import sys
import time
from urllib.parse import urlsplit

import pytest
from monitor_helpers import MonitoredRun

HANG_S = 30.0


def request(url: str, path: str, method: str = "GET", body: bytes | None = None
            ) -> tuple[int, bytes]:
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=10)
    try:
        headers = {"Content-Type": "application/json"} if body is not None else {}
        conn.request(method, path, body=body, headers=headers)
        reply = conn.getresponse()
        return reply.status, reply.read()
    finally:
        conn.close()


def drive(url: str, left: float, right: float) -> int:
    return request(url, "/drive", "POST", json.dumps({"left": left, "right": right}).encode())[0]


@pytest.fixture
def page(tmp_path):
    robot = MonitoredRun(tmp_path, command="drive", extra=("--input", "page", "--deadman", "0.2"),
                         config_extra="[monitor]\ndrive = true\n")
    yield robot
    robot.kill()


def test_the_page_drives_while_it_posts_and_the_wheels_stop_when_it_stops(page):
    url = page.url()
    deadline = time.monotonic() + HANG_S
    while json.loads(request(url, "/state")[1]).get("ticks", 0) < 5:
        assert time.monotonic() < deadline, "the drive never ticked"
        time.sleep(0.05)
    state = json.loads(request(url, "/state")[1])
    assert state["drive"] is True and page.chip.refresh().all_off()
    assert request(url, "/drive?left=1&right=1")[0] == 404  # a GET never moves a motor
    for body in (b"{}", b'{"left": 2, "right": 0}', b'{"left": NaN, "right": 0}', b"[1, 1]",
                 b"\xff", b'{"left": "1", "right": 1e400}'):
        assert request(url, "/drive", "POST", body)[0] == 400, body
    assert page.chip.refresh().all_off()
    moved = False
    end = time.monotonic() + HANG_S
    while not moved and time.monotonic() < end:  # held: a POST every 100 ms, as the page does
        assert drive(url, 1.0, 1.0) == 200
        time.sleep(0.1)
        moved = not page.chip.refresh().all_off()
    assert moved, "the page's command never reached the motors"
    released = time.monotonic()
    while not page.chip.refresh().all_off():  # let go: zero within the deadman
        assert time.monotonic() < released + HANG_S, "the wheels kept the page's command"
        time.sleep(0.01)
    assert request(url, "/stop", "POST")[0] == 200
    code, err = page.finish()
    assert code == 0, err
    assert "by hand" in "".join(page.out)


def test_the_page_cannot_drive_unless_the_config_says_so(tmp_path):
    config = tmp_path / "robot.toml"
    config.write_text("[monitor]\nlisten = \"0\"\n")
    result = subprocess.run(
        [sys.executable, "-m", "jetbot_rt.cli", "drive", "--backend", "real", "--input", "page",
         "--config", str(config), "--board-emulator", str(tmp_path / "chip.json")],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert "[monitor] drive = true" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
