"""The ``real`` backend: the camera from ``[camera] source`` through GStreamer and the drive for
``[motors] layout`` on I2C."""

from __future__ import annotations

from typing import TYPE_CHECKING

from jetbot_rt.hal.base import Backend
from jetbot_rt.hal.gst_camera import GstCamera
from jetbot_rt.hal.motors import open_drive

if TYPE_CHECKING:
    from jetbot_rt.config import Config
    from jetbot_rt.hal.registry import BackendOptions


def build_backend(config: Config, options: BackendOptions) -> Backend:
    """Open the motor board (all outputs off) and prepare the camera (started by the runtime).

    ``close`` stops the camera only: the bus stays open so that the runtime's final zero write,
    which comes after it, still reaches the board; the process exit closes it.
    """
    camera = GstCamera(config.camera, options.frame_size)
    drive = open_drive(config.motors)
    bus = drive.bus  # type: ignore[attr-defined]  # both layouts keep their I2CBus here

    def counters() -> dict[str, int]:
        return {"i2c_retried": bus.retried}

    return Backend(camera=camera, drive=drive, close=camera.stop, telemetry=counters,
                   counters=counters)
