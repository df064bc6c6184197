"""Backends that misbehave the way nobody plans for, chosen by ``BEHAVIOUR`` (set by the test
before ``main()``): the loop thread ended by SystemExit, a loop with zero completed ticks, a
backend's own thread dying. In-process, because only a backend can do these things."""

from __future__ import annotations

from jetbot_rt.testing.null_robot import NullCamera, NullDrive, PartsRobot

DRIVES: list[NullDrive] = []
BEHAVIOUR = "loop-thread-exits"


class _FramesThen(NullCamera):
    """Frames for ``good`` reads (warm-up and the first ticks), then ``then()``."""

    def __init__(self, good: int, then) -> None:
        super().__init__()
        self.good = good
        self.then = then

    def read(self):
        if self.good <= 0:
            return self.then()
        self.good -= 1
        return super().read()


def _exit_loop_thread():
    raise SystemExit("a library called sys.exit() inside a tick")


def _loop_thread_exits(config, options):
    """The loop thread ends by SystemExit from inside a tick: no exception handler sees it."""
    drive = NullDrive()
    DRIVES.append(drive)
    return PartsRobot(camera=_FramesThen(12, _exit_loop_thread), drive=drive)


def _first_tick_fails(config, options):
    """A frame for the warm-up, then none: the loop faults on its first tick (zero ticks)."""
    drive = NullDrive()
    DRIVES.append(drive)
    return PartsRobot(camera=_FramesThen(1, lambda: None), drive=drive)


def _helper_thread_dies(config, options):
    """A backend's own thread (a driver's reader) dies of an exception while the robot drives."""
    import threading
    import time

    drive = NullDrive()
    DRIVES.append(drive)

    def reader() -> None:
        time.sleep(0.4)
        raise RuntimeError("reader lost its device")

    camera = NullCamera()
    original_start = camera.start

    def start() -> None:
        original_start()
        threading.Thread(target=reader, name="camera-reader", daemon=True).start()

    camera.start = start  # type: ignore[method-assign]
    return PartsRobot(camera=camera, drive=drive)


BEHAVIOURS = {"loop-thread-exits": _loop_thread_exits, "first-tick-fails": _first_tick_fails,
              "helper-thread-dies": _helper_thread_dies}


def build_backend(config, options):
    return BEHAVIOURS[BEHAVIOUR](config, options)
