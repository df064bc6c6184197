"""Hostile input to ``jetbot-rt drive``, found by an adversarial review: a ``--gamepad-device``
that is a character device but no joystick (``/dev/zero``, an evdev node) is refused before
anything moves, and ``POST /drive`` takes JSON numbers only (``true`` or ``"1"`` would pass
``float()``); on a loopback monitor (no token) only the runtime's own user (or root) may
``POST /drive``, not every local account."""

from __future__ import annotations

import http.client
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from jetbot_rt.errors import UsageError
from jetbot_rt.monitor.config import Listen
from jetbot_rt.monitor.observer import RunView
from jetbot_rt.monitor.server import MonitorServer
from jetbot_rt.runtime.loop import LoopStats
from jetbot_rt.runtime.safety import SafeStopLatch
from jetbot_rt.teleop.gamepad import GamepadInput


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/null"])
def test_a_character_device_that_is_no_joystick_is_refused_as_a_gamepad(device):
    with pytest.raises(UsageError, match="not a joystick"):
        GamepadInput(device)


@pytest.fixture
def page() -> Iterator[tuple[int, list[tuple[float, float]]]]:
    """A loopback monitor (no token) with ``POST /drive``: its port and what it drove."""
    server = MonitorServer(Listen("127.0.0.1", 0), RunView(SafeStopLatch(), LoopStats(), 30.0,
                                                           time.monotonic()),
                           lambda _reason: None, token=None)
    driven: list[tuple[float, float]] = []
    server.on_drive = lambda left, right: driven.append((left, right))
    server.start()
    try:
        yield server.server_address[1], driven
    finally:
        server.close(linger=0)


def post(port: int, body: bytes) -> int:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("POST", "/drive", body=body)
        return conn.getresponse().status
    finally:
        conn.close()


def test_the_page_drives_only_on_json_numbers_in_range(page):
    port, driven = page
    for body in (b'{"left": true, "right": true}', b'{"left": "1", "right": "0.5"}',
                 b'{"left": null, "right": 0}', b'{"left": [1], "right": 0}',
                 b'{"left": -1.5, "right": 0}', b'"left"'):
        assert post(port, body) == 400, body
    assert not driven
    assert post(port, b'{"left": 1, "right": -0.5}') == 200
    assert driven == [(1.0, -0.5)]


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None,
                    reason="needs root and setpriv to post as another user")
def test_another_local_user_cannot_drive_through_a_loopback_page(page):
    port, driven = page
    script = ("import http.client as h, sys; "
              "c = h.HTTPConnection('127.0.0.1', int(sys.argv[1]), timeout=10); "
              "c.request('POST', '/drive', body=b'{\"left\": 1, \"right\": 1}'); "
              "print(c.getresponse().status)")
    other = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups",
                            sys.executable, "-c", script, str(port)],
                           capture_output=True, text=True, timeout=30, cwd="/")
    assert other.stdout.strip() == "403", other.stderr
    assert not driven
    assert post(port, b'{"left": 1, "right": 1}') == 200 and driven == [(1.0, 1.0)]


BACKGROUND_JOB = """
import fcntl, os, pty, sys, termios
from jetbot_rt.errors import UsageError
from jetbot_rt.teleop.keyboard import KeyboardInput
master, slave = pty.openpty()
os.setsid()
fcntl.ioctl(slave, termios.TIOCSCTTY, 0)  # our terminal, our job in its foreground
if os.fork() == 0:
    os.setpgid(0, 0)  # a job of its own: the background, as after `&` or Ctrl-Z then `bg`
    try:
        KeyboardInput(slave).close()
    except UsageError as exc:
        print(exc)
        os._exit(2)
    os._exit(0)
_, status = os.wait()
sys.exit(os.WEXITSTATUS(status))
"""


def test_the_keyboard_refuses_a_background_job_of_its_terminal():
    # before, `jetbot-rt drive --input keyboard &` was stopped by SIGTTOU at tcsetattr, and
    # once continued ended on "unexpected error: (4, 'Interrupted system call')"
    result = subprocess.run([sys.executable, "-c", BACKGROUND_JOB], capture_output=True,
                            text=True, timeout=30)
    assert result.returncode == 2, result.stderr
    assert "background job" in result.stdout
