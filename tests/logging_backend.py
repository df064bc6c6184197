"""A backend that logs, in order, what the runtime does to its drive and camera: for the exit
path's order (zero, then the robot released, then zero again as the last write)."""

from __future__ import annotations

from jetbot_rt.testing.null_robot import NullCamera, NullDrive, PartsRobot

LOG: list[str] = []


class LoggingDrive(NullDrive):
    def write(self, left: float, right: float) -> None:
        super().write(left, right)
        LOG.append("zero" if (left, right) == (0.0, 0.0) else "write")

    def stop(self) -> None:
        super().stop()
        LOG.append("zero")


class LoggingCamera(NullCamera):
    def stop(self) -> None:
        LOG.append("camera stop")


class LoggingRobot(PartsRobot):
    def disconnect(self) -> None:
        super().disconnect()
        LOG.append("disconnect")


def build_backend(config, options):
    LOG.clear()
    return LoggingRobot(camera=LoggingCamera(*options.frame_size), drive=LoggingDrive())
