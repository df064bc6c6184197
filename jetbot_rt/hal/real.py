"""The ``real`` backend: the camera from ``[camera] source`` through GStreamer and the drive for
``[motors] layout`` on I2C."""

from __future__ import annotations

from typing import TYPE_CHECKING

from jetbot_rt.hal.base import Drive, Robot
from jetbot_rt.hal.gst_camera import GstCamera
from jetbot_rt.hal.motors import open_drive

if TYPE_CHECKING:
    from jetbot_rt.config.sections import Config, MotorsConfig
    from jetbot_rt.hal.registry import BackendOptions


class RealRobot(Robot):
    """``connect`` opens the motor board (all outputs off); the camera is started by the
    runtime. ``disconnect`` stops the camera only: the bus stays open so that the runtime's
    final zero write, which comes after it, still reaches the board; the process exit closes
    it."""

    def __init__(self, camera: GstCamera, motors: MotorsConfig) -> None:
        super().__init__(camera)
        self._motors = motors

    def open_drive(self) -> Drive:
        return open_drive(self._motors)

    def state(self) -> dict[str, object]:
        return dict(self.stats())

    def stats(self) -> dict[str, float]:
        return self.drive.stats() if self.connected else {}


def build_backend(config: Config, options: BackendOptions) -> Robot:
    return RealRobot(GstCamera(config.camera, options.frame_size), config.motors)
