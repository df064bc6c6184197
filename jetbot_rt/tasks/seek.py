"""``seek``: find the red block among green/blue ones, drive to it and stop there.

Draw order from the RNG (fixed; episodes are reproducible from their seed): start noise
``dx, dy`` then ``dyaw`` (always drawn, applied only with ``start_noise``), then the goal's
distance and bearing, then the number of distractors and each one's place and colour.
Below difficulty 1 (``--curriculum``) the goal is nearer and the distractors fewer.
Why these numbers: docs/TRAINING.md ("The seek task").
"""

from __future__ import annotations

import math

import numpy as np

from jetbot_rt.tasks.goal import GOAL, GoalTask, start_pose
from jetbot_rt.tasks.goal_expert import GoalExpert
from jetbot_rt.tasks.scene import ROOM_HALF_SIZE, Block, Scene

BLOCK_AREA_HALF_SIZE = ROOM_HALF_SIZE - 0.15
"""m; block centres stay this far from the room's centre in x and y."""


def horizontal_fov_deg() -> float:
    """Of the nominal camera (``[sim] camera_vfov_deg``'s default): 82 degrees. The camera's
    geometry is the simulator's fact; its two modules read here import no physics engine."""
    from jetbot_rt.sim.camera_model import CAMERA_ASPECT
    from jetbot_rt.sim.config import SimConfig

    vfov = SimConfig().camera_vfov_deg
    half = math.atan(CAMERA_ASPECT * math.tan(math.radians(vfov) / 2))
    return math.degrees(2 * half)


def segment_distance(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """m; from ``point`` to the segment ``a``-``b``."""
    ab = b - a
    t = float(np.clip(np.dot(point - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(point - (a + t * ab)))


def in_block_area(xy: np.ndarray) -> bool:
    return bool(np.all(np.abs(xy) <= BLOCK_AREA_HALF_SIZE))


class Seek(GoalTask):
    name = "seek"
    description = "find the red block among green/blue ones, drive to it and stop there"
    robot_pose = (-0.9, 0.0, 0.0)
    episode_steps = 450
    success_distance = 0.15
    start_xy_noise = 0.05
    start_yaw_noise = 0.3
    goal_distance = (0.35, 1.2)
    """m; range of the goal's distance from the robot's start, uniform."""
    goal_fov_margin_deg = 12.0
    """The goal's bearing is uniform within the camera's horizontal field of view less this
    margin on each side, so it is in the first frame."""
    distractors = (1, 2)
    """Inclusive range of the number of distractor blocks (green or blue)."""
    curriculum = True
    easy_goal_distance = (0.35, 0.5)
    """m; ``goal_distance`` at difficulty 0 (``--curriculum``): the goal near, big in the first
    frame; the far end widens linearly to 1.2 m at difficulty 1."""
    easy_distractors = (0, 0)
    """``distractors`` at difficulty 0: none; one from difficulty 0.5, up to two at 1."""
    min_block_spacing = 0.25
    """m; between any two block centres."""
    path_clearance = 0.15
    """m; distractors stay this far from the straight line between the start and the goal."""
    stop_speed = 0.01
    max_block_shift = 0.03
    early_end = True
    max_speed = 0.5
    randomize = True
    # Why these numbers: docs/TRAINING.md ("Training seek").
    training = {  # noqa: RUF012 - read only
        "total_timesteps": 300_000, "out": "runs/seek", "reward_transform": "none",
        "shaping_coef": 10.0, "aim_coef": 5.0, "success_bonus": 10.0, "fail_penalty": 5.0,
        "learning_rate": 3e-4, "update_epochs": 8, "num_minibatches": 4,  # as measured
        "model": {"init_mu": 0.3},
    }

    def scene(self, rng: np.random.Generator, start_noise: bool) -> Scene:
        robot = start_pose(self, rng, start_noise)
        x, y, yaw = robot
        start = np.array([x, y])
        half_fov = math.radians(horizontal_fov_deg() / 2)
        goal_bearing = half_fov - math.radians(self.goal_fov_margin_deg)

        def place(distance: float, bearing: float) -> np.ndarray:
            return start + distance * np.array([math.cos(yaw + bearing), math.sin(yaw + bearing)])

        goal_distance = self.between(self.easy_goal_distance, self.goal_distance)
        distractors = self.between(self.easy_distractors, self.distractors)
        goal = place(rng.uniform(*goal_distance), rng.uniform(-goal_bearing, goal_bearing))
        blocks = [goal]
        pieces = [Block((float(goal[0]), float(goal[1])), name=GOAL)]
        count = int(rng.integers(distractors[0], distractors[1] + 1))
        for _ in range(count):
            for _attempt in range(200):
                where = place(rng.uniform(0.3, goal_distance[1] + 0.2),
                              rng.uniform(-half_fov, half_fov))
                color = str(rng.choice(("green", "blue")))
                if (in_block_area(where)
                        and min(np.linalg.norm(where - b) for b in blocks)
                        >= self.min_block_spacing
                        and segment_distance(where, start, goal) >= self.path_clearance):
                    blocks.append(where)
                    pieces.append(Block((float(where[0]), float(where[1])), color))
                    break
        return Scene(robot, tuple(pieces))

    def expert(self) -> GoalExpert:
        return GoalExpert()
