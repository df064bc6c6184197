"""Who is on the other end of a loopback TCP connection: the uid the kernel lists for the
client's socket in ``/proc/net/tcp`` (``tcp6``). A monitor on loopback has no token (reach it
with ``ssh -L``), so without this any local account could ``POST /drive`` and move the motors;
``POST /drive`` there is taken from the runtime's own user (or root) only. Unknown (no
``/proc``, the socket already gone): refused, the drive is the thing to keep closed."""

from __future__ import annotations

import ipaddress
import os
import socket
from typing import Any

TABLES = {socket.AF_INET: "/proc/net/tcp", socket.AF_INET6: "/proc/net/tcp6"}


def _hex_address(host: str, port: int) -> str:
    """The kernel's text for an address: each 32-bit word in host order, as hex."""
    packed = ipaddress.ip_address(host.split("%", 1)[0]).packed
    words = [packed[i:i + 4] for i in range(0, len(packed), 4)]
    text = "".join(int.from_bytes(w, "little" if socket.htonl(1) != 1 else "big")
                   .to_bytes(4, "big").hex().upper() for w in words)
    return f"{text}:{port:04X}"


def peer_uid(family: int, client: Any, server: Any) -> int | None:
    """The uid owning the client end (``client`` -> ``server``), or None if not found."""
    try:
        local = _hex_address(client[0], int(client[1]))
        remote = _hex_address(server[0], int(server[1]))
        with open(TABLES[family], encoding="ascii") as table:
            next(table, None)
            for line in table:
                fields = line.split()
                if len(fields) > 7 and fields[1] == local and fields[2] == remote:
                    return int(fields[7])
    except (OSError, ValueError, KeyError, UnicodeDecodeError):
        return None
    return None


def trusted_uids() -> set[int]:
    """The runtime's own user, root, and under sudo the user who ran it."""
    uids = {os.getuid(), os.geteuid(), 0}
    sudo = os.environ.get("SUDO_UID", "")
    if os.geteuid() == 0 and sudo.isdigit():
        uids.add(int(sudo))
    return uids
