"""A backend whose camera fails with an error nobody planned for (a driver bug)."""

from __future__ import annotations

from jetbot_rt.testing.null_robot import NullCamera, NullDrive, PartsRobot

DRIVES: list[NullDrive] = []


class BrokenCamera(NullCamera):
    def start(self) -> None:
        raise RuntimeError("driver bug")


def build_backend(config, options):
    drive = NullDrive()
    drive.last = (0.5, 0.5)  # as if a previous owner left the board driving
    DRIVES.append(drive)
    return PartsRobot(camera=BrokenCamera(), drive=drive)

