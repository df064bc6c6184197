"""Who is on the other end of a loopback TCP connection: the uid the kernel lists for the
client's socket in ``/proc/net/tcp`` (``tcp6``). A monitor on loopback has no token (reach it
with ``ssh -L``), so without this any local account could ``POST /drive`` and move the motors;
``POST /drive`` there is taken from the runtime's own user (or root) only. Unknown (no
``/proc``, the socket already gone, a table past ``MAX_TABLE_BYTES``): refused, the drive is the
thing to keep closed.

The table lists every TCP socket of the network namespace (about 150 bytes each) and the page
posts ten times a second, so it is read through ``safe_file`` within ``MAX_TABLE_BYTES``:
another account that opens thousands of sockets makes the page's drive refused, never a
handler thread that parses megabytes under the GIL beside the 30 Hz tick. A line is split only
when it holds the connection's two addresses (a byte search)."""

from __future__ import annotations

import contextlib
import ipaddress
import os
import socket
from typing import Any

from jetbot_rt.config import safe_file
from jetbot_rt.errors import UsageError

TABLES = {socket.AF_INET: "/proc/net/tcp", socket.AF_INET6: "/proc/net/tcp6"}
MAX_TABLE_BYTES = safe_file.MIB
"""About 7,000 sockets; a robot has tens."""
MAX_LINE_BYTES = 512


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
        local = _hex_address(client[0], int(client[1])).encode("ascii")
        remote = _hex_address(server[0], int(server[1])).encode("ascii")
        lines = safe_file.iter_lines(TABLES[family], "the TCP table", MAX_TABLE_BYTES,
                                     MAX_LINE_BYTES)
        with contextlib.closing(lines):  # the descriptor closed also on a match
            for number, line, _ in lines:
                if number == 1 or local + b" " + remote not in line:
                    continue
                fields = line.split()
                if len(fields) > 7 and fields[1] == local and fields[2] == remote:
                    return int(fields[7])
    except (UsageError, ValueError, KeyError):
        return None
    return None


def trusted_uids() -> set[int]:
    """The runtime's own user, root, and under sudo the user who ran it."""
    uids = {os.getuid(), os.geteuid(), 0}
    sudo = os.environ.get("SUDO_UID", "")
    if os.geteuid() == 0 and sudo.isdigit():
        uids.add(int(sudo))
    return uids
