"""Park in front of the blue wall: a task of your own, in one file (docs/TASKS.md walks
through it).

A blue wall stands across the robot's way, 0.6 to 1.0 m ahead, with an orange box beside the
path. Success: the robot stands still with its axle 12 to 22 cm from the wall's face, never
having touched it. Touching the wall ends the episode.

Train, evaluate and drive it:

    jetbot-train train --task examples/tasks/my_task.py:ParkAtBlueWall --out runs/park
    jetbot-train eval --task examples/tasks/my_task.py:ParkAtBlueWall --policy runs/park/policy.onnx
    # a config with [sim] task = "examples/tasks/my_task.py:ParkAtBlueWall", then
    jetbot-rt run --backend sim --config park.toml --policy runs/park/policy.onnx
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jetbot_rt.tasks import Box, Scene, Task, Wall

WALL_THICKNESS = 0.04
PARK_NEAR, PARK_FAR = 0.12, 0.22
"""m, axle to the wall's face: where the robot must stop."""


class ParkAtBlueWall(Task):
    name = "park"
    description = "stop 12-22 cm in front of the blue wall without touching it"
    episode_steps = 300  # 10 s at 30 Hz
    max_speed = 0.3
    training = {"total_timesteps": 60_000}  # noqa: RUF012 - read only

    def scene(self, rng: np.random.Generator, start_noise: bool) -> Scene:
        # Draw every number whatever start_noise says: the pieces of a seed stay the same.
        noise = rng.uniform(-0.05, 0.05, 3)
        x, y, yaw = -0.8, 0.0, 0.0
        if start_noise:
            x, y, yaw = x + noise[0], y + noise[1], yaw + 2 * noise[2]
        face = x + rng.uniform(0.6, 1.0)  # the wall's face, ahead of the robot
        middle = rng.uniform(-0.15, 0.15)
        wall_x = face + WALL_THICKNESS / 2
        side = rng.choice((-1.0, 1.0))
        return Scene(
            robot_pose=(x, y, yaw),
            pieces=(
                Wall((wall_x, middle - 0.4), (wall_x, middle + 0.4), color="blue",
                     thickness=WALL_THICKNESS, height=0.15, name="wall"),
                Box((face - 0.3, middle + side * 0.45), size=(0.1, 0.1, 0.1), color="orange"),
            ),
        )

    def outcome(self, scene: Scene, world: Any) -> dict[str, Any]:
        x, _, yaw = world.robot_pose()
        wall = scene.piece("wall")
        gap = wall.start[0] - WALL_THICKNESS / 2 - x
        speed = world.robot_speed()
        touching = world.touching("wall")
        return {
            "gap": gap,
            "distance": abs(gap - (PARK_NEAR + PARK_FAR) / 2),  # what eval's summary prints
            "speed": speed,
            "touching": touching,
            "is_success": bool(PARK_NEAR <= gap <= PARK_FAR and speed < 0.02 and not touching),
            "heading": yaw,
        }

    def reward(self, info: dict[str, Any]) -> float:
        # Dense enough for PPO: closer to the parking band is better, touching costs.
        reward = -abs(info["gap"] - (PARK_NEAR + PARK_FAR) / 2)
        if info["touching"]:
            reward -= 5.0
        if info["is_success"]:
            reward += 1.0
        return reward

    def terminated(self, info: dict[str, Any]) -> bool:
        return bool(info["touching"])

    def expert(self) -> ParkExpert:
        return ParkExpert()


class ParkExpert:
    """A privileged teacher for ``--algo dagger``: it reads the true gap and heading (never
    the image) and drives straight at the wall, stopping in the middle of the band."""

    reads = ("gap", "heading")

    def label(self, info: dict[str, Any]) -> np.ndarray:
        beyond = float(info["gap"]) - (PARK_NEAR + PARK_FAR) / 2
        if beyond <= 0.0:
            return np.zeros(2, dtype=np.float32)
        forward = min(1.0, 0.4 + 3.0 * beyond)
        turn = float(np.clip(-2.0 * math.sin(float(info["heading"])), -0.5, 0.5))
        return np.clip(np.array([forward - turn, forward + turn], dtype=np.float32), -1, 1)
