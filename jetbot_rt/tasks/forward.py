"""``forward``: drive to a red block 0.9 m straight ahead (the default task).

Why these numbers: docs/TRAINING.md ("The forward task").
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jetbot_rt.tasks.goal import GOAL, GoalTask, start_pose
from jetbot_rt.tasks.scene import Block, Scene

MIN_REWARD_DISTANCE = 0.01
"""m; the reward's 1/d is evaluated at no less than this (bodies never get this close)."""


def forward_reward(distance: float) -> float:
    """forward's reward, ``exp(1/d) - 30``."""
    return math.exp(1.0 / max(distance, MIN_REWARD_DISTANCE)) - 30.0


class Forward(GoalTask):
    name = "forward"
    description = "drive to a red block 0.9 m straight ahead (the default task)"
    robot_pose = (-0.6, 0.0, 0.0)
    goal_xy = (0.3, 0.0)
    episode_steps = 450
    success_distance = 0.15
    start_xy_noise = 0.02
    start_yaw_noise = 0.15
    # The trainer's shaping on distance and aim_error (docs/TRAINING.md, "PPO"); a 6x6
    # stride-4 first layer: a quarter of the network's CPU (docs/TRAINING.md, "Speed").
    training = {  # noqa: RUF012 - read only
        "shaping_coef": 1000.0, "aim_coef": 300.0,
        "model": {"first_kernel": 6, "first_stride": 4},
    }

    def scene(self, rng: np.random.Generator, start_noise: bool) -> Scene:
        return Scene(start_pose(self, rng, start_noise), (Block(self.goal_xy, name=GOAL),))

    def reward(self, info: dict[str, Any]) -> float:
        return forward_reward(info["distance"])
