"""The live page of a run (``jetbot-rt run --monitor``, ``[monitor]``): docs/MONITOR.md.

``config`` is read by ``Config`` and imports nothing heavy; ``start`` opens the server."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

from jetbot_rt.errors import UsageError

if TYPE_CHECKING:
    from jetbot_rt.monitor.config import MonitorConfig
    from jetbot_rt.monitor.observer import RunView
    from jetbot_rt.monitor.server import MonitorServer


def start(config: MonitorConfig, view: RunView, on_stop: Callable[[str], None],
          say: Callable[[str], Any] = print) -> MonitorServer:
    """Bind (a port in use or an address not ours is bad input: ``UsageError``, before the
    robot connects), settle the token, serve in threads of its own."""
    import errno
    import ipaddress

    from jetbot_rt.monitor import token as tokens
    from jetbot_rt.monitor.server import MonitorServer

    listen = config.address
    assert listen is not None
    token = None
    new_token = False
    if not listen.loopback:
        token, new_token = tokens.load_or_create(config.token_file)
    try:
        server = MonitorServer(listen, view, on_stop, token, config.max_fps)
    except OSError as exc:
        why = ("the port is in use" if exc.errno == errno.EADDRINUSE
               else exc.strerror or str(exc))
        raise UsageError(f"--monitor {listen.url_host}:{listen.port}: cannot listen: {why}") \
            from None
    server.start()
    say(f"monitor: {server.url} (read-only page and API, one STOP; docs/MONITOR.md)")
    if token is not None:
        if new_token:
            where = (f", saved in {config.token_file} (mode 0600)" if config.token_file
                     else "")
            url = server.url
            if ipaddress.ip_address(listen.host).is_unspecified:  # every address: name none
                url = f"http://<this machine>:{server.server_address[1]}/"
            say(f"monitor: token required on {listen.host}; open {url}?token={token} "
                f"once{where}")
        else:
            say(f"monitor: token required on {listen.host}: the one in {config.token_file}")
    return server
