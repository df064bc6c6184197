"""``--input page``: hold-to-drive buttons on the monitor's page (docs/MONITOR.md), only with
``[monitor] drive = true`` (off by default) and the monitor listening.

While a button is held the page sends ``POST /drive {"left": L, "right": R}`` every 100 ms,
under the monitor's access rules (the token off loopback, the Origin check of STOP); each is
a command valid for the deadman. A released button, a closed or hidden tab, a dropped network
all end the same way: no more requests, and the command expires within the deadman (the
server cannot tell them apart; none is an ``input_lost``). Nothing moves on a GET.
"""

from __future__ import annotations

from typing import Any

from jetbot_rt.teleop.hand import DEADMAN_S, HandCommand, HandInput


class PageInput(HandInput):
    name = "page"

    def __init__(self, server: Any, deadman_s: float = DEADMAN_S) -> None:
        super().__init__(deadman_s)
        self.server = server

    def start(self) -> None:
        self.server.on_drive = self._post

    def _post(self, left: float, right: float) -> None:
        self.propose(HandCommand((left, right), takeover=True))

    def close(self) -> None:
        self.server.on_drive = None
