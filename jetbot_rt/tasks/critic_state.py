"""Pieces of the built-in tasks' privileged critic states (``Task.critic_state``): the robot's
frame, the wheel commands it last sent and the episode's ``[sim]`` knobs that change how it
moves, each scaled to about unit size.

Why these: an image-only critic has to guess from one frame how far the goal is, how fast
the robot goes and how late its commands act; the state critic is told. The wheel commands
of the last tick matter because of the command latency (up to 0.2 s randomized: six ticks of
commands still on their way) and the motor's lag; the dynamics knobs because the same picture
is worth more to a strong, prompt robot than to one with a wide dead-band and a weak wheel.
The scales only keep the critic's inputs near unit size; nothing depends on their exact values.
"""

from __future__ import annotations

import math
from typing import Any

DYNAMICS: tuple[tuple[str, float, float], ...] = (
    ("motor_gain", 20.0, 20.0),
    ("deadband", 0.0, 0.3),
    ("latency", 0.0, 0.2),
    ("camera_latency", 0.0, 0.12),
)
"""(``[sim]`` key, its default, its scale): the scalar knobs of ``info["sim_params"]`` a
state critic reads (the default where the info has none). The scales are the tops of
``[randomize]``'s default ranges (the motor gain's: its nominal value)."""
DYNAMICS_NAMES = (*(name for name, _, _ in DYNAMICS), "wheel_gain_left", "wheel_gain_right",
                  "stall_torque")
COMMAND_NAMES = ("command_left", "command_right")
STALL_TORQUE_SCALE = 0.1
"""N m; ``[randomize] stall_torque``'s top. The ideal motor (no stall torque) reads 0."""


def robot_frame(pose: Any, xy: Any) -> tuple[float, float]:
    """(ahead, left) in m: the point ``xy`` in the frame of the robot at ``pose``."""
    x, y, yaw = (float(v) for v in pose)
    dx, dy = float(xy[0]) - x, float(xy[1]) - y
    return (math.cos(yaw) * dx + math.sin(yaw) * dy, -math.sin(yaw) * dx + math.cos(yaw) * dy)


def commands(info: dict[str, Any], max_speed: float) -> list[float]:
    """The duties the last tick wrote (``info["duty"]``) over the task's ``max_speed``: about
    the policy's last action after the clamp, trim and sign."""
    left, right = (float(d) / max_speed for d in info["duty"])
    return [left, right]


def dynamics(info: dict[str, Any]) -> list[float]:
    """The values of ``DYNAMICS_NAMES`` from ``info["sim_params"]`` (defaults without it)."""
    params = info.get("sim_params") or {}
    values = [float(params.get(key, default)) / scale for key, default, scale in DYNAMICS]
    gains = params.get("wheel_gain") or (1.0, 1.0)
    stall = params.get("stall_torque")
    return [*values, float(gains[0]), float(gains[1]),
            0.0 if stall is None else float(stall) / STALL_TORQUE_SCALE]


__all__ = ["COMMAND_NAMES", "DYNAMICS", "DYNAMICS_NAMES", "commands", "dynamics", "robot_frame"]
