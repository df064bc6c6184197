"""``jetbot_rt.monitor.peer``: who is on the other end of a loopback connection to the
monitor, read from the kernel's TCP table within a bound."""

from __future__ import annotations

import os
import socket

from jetbot_rt.monitor import peer


def test_the_peer_of_a_loopback_connection_is_found_and_a_huge_tcp_table_is_refused(monkeypatch):
    with socket.create_server(("127.0.0.1", 0)) as listener, \
            socket.create_connection(listener.getsockname(), timeout=10) as client:
        server_end, _ = listener.accept()
        with server_end:
            args = (socket.AF_INET, client.getsockname(), listener.getsockname())
            assert peer.peer_uid(*args) == os.geteuid()
            # a table past the bound (another account's thousands of sockets): unknown,
            # so refused, rather than megabytes parsed beside the tick
            bound = peer.MAX_TABLE_BYTES
            monkeypatch.setattr(peer, "MAX_TABLE_BYTES", 100)
            assert peer.peer_uid(*args) is None
            monkeypatch.setattr(peer, "MAX_TABLE_BYTES", bound)
            assert peer.peer_uid(socket.AF_INET, ("127.0.0.1", 1), ("127.0.0.1", 2)) is None
