"""The ``[monitor]`` section: where the live page listens and where its token lives.

Owned here, beside the server it configures (``config/sections.py`` only includes it). The
annotations are ``Optional[...]``: the robot's Python 3.8 evaluates them.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

from jetbot_rt.config.schema import check, within

DEFAULT_HOST = "127.0.0.1"
LISTEN_SPELLED = '"[HOST:]PORT" with HOST an IP address or localhost and PORT in 0..65535'


class Listen(NamedTuple):
    host: str
    port: int

    @property
    def loopback(self) -> bool:
        return ipaddress.ip_address(self.host).is_loopback

    @property
    def url_host(self) -> str:
        return f"[{self.host}]" if ":" in self.host else self.host


def parse_listen(value: str) -> Listen:
    """``"8080"`` -> 127.0.0.1:8080; ``"0.0.0.0:8080"``, ``"[::1]:8080"``, ``"localhost:80"``.
    Only IP literals (and ``localhost``): a name would need DNS at start, and what it resolves
    to decides whether a token is required. ``ValueError`` says what is wrong."""
    text = value.strip()
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host, port_text = DEFAULT_HOST, text
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        raise ValueError(f"{LISTEN_SPELLED} (an IPv6 address in brackets), got {value!r}")
    if host == "localhost":
        host = DEFAULT_HOST
    try:
        host = str(ipaddress.ip_address(host))
    except ValueError:
        raise ValueError(f"{LISTEN_SPELLED}, got {value!r}") from None
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ValueError(f"{LISTEN_SPELLED}, got {value!r}")
    return Listen(host, int(port_text))


def _listen_ok(value: str) -> bool:
    parse_listen(value)  # raises ValueError with the whole message
    return True


@dataclass
class MonitorConfig:
    listen: Optional[str] = field(default=None, metadata=check(_listen_ok, LISTEN_SPELLED))
    """Serve the live page (docs/MONITOR.md) on ``[HOST:]PORT``; off by default. HOST defaults
    to 127.0.0.1 (reach it with ``ssh -L``); any other address requires the token.
    ``--monitor`` overrides."""
    token_file: Optional[str] = field(default=None, metadata=check(bool, "a file name, not empty"))
    """The token a non-loopback monitor requires: read from this file when it exists (it must
    be a regular file nobody else may read or write, mode 0600), else generated at start and
    written here with mode 0600. Without it a generated token is only printed."""
    drive: bool = False
    """Let the page drive (``jetbot-rt drive --input page``, docs/DRIVE.md): hold-to-drive
    buttons that ``POST /drive`` a command every 100 ms, under the same access rules as STOP
    (the token off loopback). Off by default: the page is read-only but for STOP."""
    max_fps: float = field(default=15.0, metadata=within(1.0, 60.0, " Hz"))
    """The most frames (and state updates) a second each client is sent; a slower client gets
    fewer, counted as dropped."""

    @property
    def address(self) -> Listen | None:
        return parse_listen(self.listen) if self.listen is not None else None
