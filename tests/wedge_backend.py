"""A backend whose camera wedges the whole interpreter: after ``GOOD_FRAMES`` reads, ``read()``
calls a native function that never returns and never releases the GIL (as a C extension that
blocks without ``Py_BEGIN_ALLOW_THREADS`` would). No Python code of any thread runs again, the
runtime's own watchdog thread included: the case systemd's watchdog and its
``FinalKillSignal`` exist for.

Run in a subprocess: ``python wedge_backend.py run --backend wedge ...`` is ``jetbot-rt``
with this backend registered."""

from __future__ import annotations

import ctypes
import signal
import sys

from jetbot_rt.testing.null_robot import NullCamera, PartsRobot

GOOD_FRAMES = 10


class WedgingCamera(NullCamera):
    def __init__(self) -> None:
        super().__init__()
        self.reads = 0

    def read(self):  # type: ignore[no-untyped-def]
        self.reads += 1
        if self.reads > GOOD_FRAMES:
            wedge_holding_the_gil()
        return super().read()


def wedge_holding_the_gil() -> None:
    # No signal interrupts the sleep (each would end it early): they go to other threads,
    # whose C handlers only note them; the Python handlers wait for the GIL for ever.
    signal.pthread_sigmask(signal.SIG_BLOCK, signal.valid_signals())
    while True:
        ctypes.pythonapi.sleep(3600)  # a PyDLL function: called with the GIL held


def build_backend(config, options):  # type: ignore[no-untyped-def]
    return PartsRobot(camera=WedgingCamera())


if __name__ == "__main__":
    from jetbot_rt.cli import main
    from jetbot_rt.hal import registry

    registry.BACKEND_MODULES["wedge"] = "wedge_backend"
    sys.exit(main(sys.argv[1:]))
