"""A camera that always has a fresh constant frame and a drive that only remembers the last
write. Used by the benchmarks to measure the loop itself, and by tests of the loop."""

from __future__ import annotations

import time

import numpy as np

from jetbot_rt.hal.base import DEFAULT_FRAME_SIZE, Camera, Drive, Frame, Robot


class NullCamera(Camera):
    def __init__(self, width: int = DEFAULT_FRAME_SIZE[0],
                 height: int = DEFAULT_FRAME_SIZE[1]) -> None:
        self._image = np.full((height, width, 3), 128, dtype=np.uint8)
        self._count = 0

    def start(self) -> None:
        pass

    def read(self) -> Frame:
        self._count += 1
        return Frame(self._image, time.monotonic(), self._count)

    def stop(self) -> None:
        pass


class NullDrive(Drive):
    def __init__(self) -> None:
        self.last: tuple[float, float] = (0.0, 0.0)
        self.writes = 0

    def write(self, left: float, right: float) -> None:
        self.last = (left, right)
        self.writes += 1

    def stop(self) -> None:
        self.last = (0.0, 0.0)
        self.writes += 1


class PartsRobot(Robot):
    """A robot made of given parts (a null camera and drive unless told): for the loop's
    benchmarks and tests, which bring their own cameras and drives."""

    def __init__(self, camera: Camera | None = None, drive: Drive | None = None) -> None:
        super().__init__(camera or NullCamera())
        self._parts_drive = drive or NullDrive()

    def open_drive(self) -> Drive:
        return self._parts_drive

