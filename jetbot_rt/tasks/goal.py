"""Reach a goal block: the common part of ``forward`` and ``seek``, and a base for tasks like
them. The goal is the ``Block`` named ``"goal"``; ``outcome`` reports how far the robot is
from it, how far it has been pushed, the robot's speed, and how far the goal lies off the
robot's line of travel (``aim_error``, which the trainer's aim shaping reads).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from jetbot_rt.tasks.api import Task, WorldView
from jetbot_rt.tasks.critic_state import (
    COMMAND_NAMES,
    DYNAMICS_NAMES,
    commands,
    dynamics,
    robot_frame,
)
from jetbot_rt.tasks.scene import Block, Scene

GOAL = "goal"
SPEED_SCALE = 0.3
"""m/s; about the fastest a randomized robot drives (the critic state's speed unit)."""
SHIFT_SCALE = 0.03
"""m; seek's ``max_block_shift`` (the critic state's block shift unit)."""


def start_pose(task: GoalTask, rng: np.random.Generator,
               start_noise: bool) -> tuple[float, float, float]:
    """The nominal pose with uniform noise; the three numbers are drawn either way (dx, dy,
    then dyaw), so a seed's pieces do not depend on ``start_noise``."""
    x, y, yaw = task.robot_pose
    dx, dy = rng.uniform(-task.start_xy_noise, task.start_xy_noise, 2)
    dyaw = rng.uniform(-task.start_yaw_noise, task.start_yaw_noise)
    if start_noise:
        x, y, yaw = x + float(dx), y + float(dy), yaw + float(dyaw)
    return (x, y, yaw)


def aim_error(world: WorldView, name: str = GOAL) -> float:
    """m; how far a piece's centre lies from the robot's line of travel (the distance to it
    when it is beside or behind the robot). 0 when aimed straight at it."""
    x, y, yaw = world.robot_pose()
    bx, by, _ = world.position(name)
    dx, dy = bx - x, by - y
    bearing = math.atan2(dy, dx) - yaw
    bearing = abs(math.atan2(math.sin(bearing), math.cos(bearing)))
    return math.hypot(dx, dy) * math.sin(min(bearing, math.pi / 2))


class GoalTask(Task):
    """Drive the robot's axle midpoint to within ``success_distance`` of the goal block
    (optionally slower than ``stop_speed``, the block moved less than ``max_block_shift``)."""

    robot_pose: ClassVar[tuple[float, float, float]] = (-0.6, 0.0, 0.0)
    """Nominal start (x, y, yaw) of the robot's axle midpoint."""
    start_xy_noise: ClassVar[float] = 0.0
    """m; uniform +- noise on the start x and y."""
    start_yaw_noise: ClassVar[float] = 0.0
    """rad; uniform +- noise on the start yaw."""
    success_distance: ClassVar[float | None] = 0.15
    stop_speed: ClassVar[float | None] = None
    """m/s; if set, success also needs the robot slower than this."""
    max_block_shift: ClassVar[float | None] = None
    """m; if set, success also needs the goal moved less than this from where it was put;
    moved that far or more, the episode has ``failed``."""
    early_end: ClassVar[bool] = False
    """End the episode at the first step that succeeds or fails."""

    def scene(self, rng: np.random.Generator, start_noise: bool) -> Scene:
        raise NotImplementedError

    def outcome(self, scene: Scene, world: WorldView) -> dict[str, Any]:
        distance = world.distance(GOAL)
        shift = world.shift(GOAL)
        speed = world.robot_speed()
        success = distance < self.success_distance
        if self.stop_speed is not None:
            success = success and speed < self.stop_speed
        if self.max_block_shift is not None:
            success = success and shift < self.max_block_shift
        failed = self.max_block_shift is not None and shift >= self.max_block_shift
        goal = scene.piece(GOAL)
        assert isinstance(goal, Block)
        return {"distance": distance, "block_shift": shift, "speed": speed,
                "is_success": bool(success), "failed": bool(failed),
                "aim_error": aim_error(world), "goal_xy": np.array(goal.xy)}

    def terminated(self, info: dict[str, Any]) -> bool:
        return self.early_end and bool(info["is_success"] or info["failed"])

    critic_state_names = ("goal_distance", "goal_bearing_sin", "goal_bearing_cos",
                          "block_shift", "speed", *COMMAND_NAMES, *DYNAMICS_NAMES)

    def critic_state(self, info: dict[str, Any]) -> np.ndarray:
        """The goal's distance (m) and bearing in the robot's frame (sine and cosine: no
        jump behind the robot; from where it was placed, which it leaves by less than
        ``max_block_shift`` in a live seek episode), how far it has been pushed (in 3 cm),
        the robot's speed (in 0.3 m/s), the last wheel commands and the episode's dynamics
        (``critic_state.py``). What the value of a frame depends on that one frame shows
        badly or not at all: the distance to a small block, the speed, latency."""
        ahead, left = robot_frame(info["pose"], info["goal_xy"])
        bearing = math.atan2(left, ahead)
        return np.array([float(info["distance"]), math.sin(bearing), math.cos(bearing),
                         float(info["block_shift"]) / SHIFT_SCALE,
                         float(info["speed"]) / SPEED_SCALE,
                         *commands(info, self.max_speed), *dynamics(info)], dtype=np.float32)
