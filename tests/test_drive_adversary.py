"""Hostile input to ``jetbot-rt drive``, found by an adversarial review: a ``--gamepad-device``
that is a character device but no joystick (``/dev/zero``, an evdev node) is refused before
anything moves, and ``POST /drive`` takes JSON numbers only (``true`` or ``"1"`` would pass
``float()``)."""

from __future__ import annotations

import http.client
import time

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


def test_the_page_drives_only_on_json_numbers_in_range():
    server = MonitorServer(Listen("127.0.0.1", 0), RunView(SafeStopLatch(), LoopStats(), 30.0,
                                                           time.monotonic()),
                           lambda _reason: None, token=None)
    driven: list[tuple[float, float]] = []
    server.on_drive = lambda left, right: driven.append((left, right))
    server.start()
    port = server.server_address[1]

    def post(body: bytes) -> int:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        try:
            conn.request("POST", "/drive", body=body)
            return conn.getresponse().status
        finally:
            conn.close()

    try:
        for body in (b'{"left": true, "right": true}', b'{"left": "1", "right": "0.5"}',
                     b'{"left": null, "right": 0}', b'{"left": [1], "right": 0}',
                     b'{"left": -1.5, "right": 0}', b'"left"'):
            assert post(body) == 400, body
        assert not driven
        assert post(b'{"left": 1, "right": -0.5}') == 200
        assert driven == [(1.0, -0.5)]
    finally:
        server.close(linger=0)
