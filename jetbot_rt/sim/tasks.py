"""The tasks: where a scene puts the robot and the blocks, and what counts as success.

Pure geometry on numpy (no pybullet until a scene is checked against a world), shared by the
Gymnasium env and the ``sim`` backend of ``jetbot-rt run``, so that ``reset(seed=s,
options={"start_noise": False})`` and ``[sim] seed = s`` build the same scene.

Draw order from the RNG (fixed; episodes are reproducible from their seed): start noise
``dx, dy`` then ``dyaw`` (always drawn, applied only with ``start_noise``), then the goal's
distance and bearing, then the number of distractors and each one's place and colour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from jetbot_rt.errors import UsageError

if TYPE_CHECKING:
    from jetbot_rt.sim.world import JetbotWorld

ROOM_HALF_SIZE = 1.35
"""m; block centres stay this far from the room's centre in x and y (walls at 1.5)."""


@dataclass(frozen=True)
class Task:
    name: str
    description: str
    robot_pose: tuple[float, float, float]
    """Nominal start (x, y, yaw) of the robot's axle midpoint."""
    episode_steps: int
    """Time limit in control ticks (``truncated``)."""
    success_distance: float
    """m; success needs the robot's base (axle midpoint) closer than this to the goal's centre."""
    start_xy_noise: float
    """m; uniform +- noise on the start x and y."""
    start_yaw_noise: float
    """rad; uniform +- noise on the start yaw."""
    block_xy: tuple[float, float] | None = None
    """A fixed goal position (forward); None: placed relative to the robot (seek)."""
    goal_distance: tuple[float, float] = (0.0, 0.0)
    """m; range of the goal's distance from the robot's start, uniform."""
    goal_fov_margin_deg: float = 0.0
    """The goal's bearing is uniform within the camera's horizontal field of view less this
    margin on each side, so it is in the first frame."""
    distractors: tuple[int, int] = (0, 0)
    """Inclusive range of the number of distractor blocks (green or blue)."""
    min_block_spacing: float = 0.25
    """m; between any two block centres."""
    path_clearance: float = 0.15
    """m; distractors stay this far from the straight line between the start and the goal."""
    stop_speed: float | None = None
    """m/s; if set, success also needs the robot slower than this."""
    max_block_shift: float | None = None
    """m; if set, success also needs the goal moved less than this from where it was put."""
    early_end: bool = False
    """End the episode (``terminated``) at the first step that succeeds, or once the goal has
    moved ``max_block_shift`` or more (it cannot succeed any more)."""
    max_speed: float = 0.1
    """Duty at |mu| = 1 the task trains with (exported into the policy's metadata)."""
    randomize: bool = False
    """Domain randomization ([randomize] ranges) unless the env or the config says otherwise."""


TASKS: dict[str, Task] = {
    # Why these numbers: docs/TRAINING.md ("The forward task").
    "forward": Task(
        name="forward",
        description="drive to a red block 0.9 m straight ahead (the default task)",
        robot_pose=(-0.6, 0.0, 0.0),
        block_xy=(0.3, 0.0),
        episode_steps=450,
        success_distance=0.15,
        start_xy_noise=0.02,
        start_yaw_noise=0.15,
    ),
    # Why these numbers: docs/TRAINING.md ("The seek task").
    "seek": Task(
        name="seek",
        description="find the red block among green/blue ones, drive to it and stop there",
        robot_pose=(-0.9, 0.0, 0.0),
        episode_steps=450,
        success_distance=0.15,
        start_xy_noise=0.05,
        start_yaw_noise=0.3,
        goal_distance=(0.35, 1.2),
        goal_fov_margin_deg=12.0,
        distractors=(1, 2),
        stop_speed=0.01,
        max_block_shift=0.03,
        early_end=True,
        max_speed=0.5,
        randomize=True,
    ),
}


def get_task(name: str) -> Task:
    if name not in TASKS:
        raise UsageError(f"unknown task {name!r} (known: {', '.join(sorted(TASKS))})")
    return TASKS[name]


@dataclass(frozen=True)
class Scene:
    robot_pose: tuple[float, float, float]
    goal_xy: tuple[float, float]
    distractors: tuple[tuple[float, float, str], ...] = ()


def horizontal_fov_deg() -> float:
    """Of the nominal camera (``[sim] camera_vfov_deg``'s default): 82 degrees."""
    from jetbot_rt.sim.camera_model import CAMERA_ASPECT
    from jetbot_rt.sim.config import SimConfig

    vfov = SimConfig().camera_vfov_deg
    half = math.atan(CAMERA_ASPECT * math.tan(math.radians(vfov) / 2))
    return math.degrees(2 * half)


def _segment_distance(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(point - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(point - (a + t * ab)))


def _in_room(xy: np.ndarray) -> bool:
    return bool(np.all(np.abs(xy) <= ROOM_HALF_SIZE))


def sample_scene(task: Task, rng: np.random.Generator, start_noise: bool = True) -> Scene:
    """The scene of one episode, drawn from ``rng`` in the module's fixed order."""
    x, y, yaw = task.robot_pose
    dx, dy = rng.uniform(-task.start_xy_noise, task.start_xy_noise, 2)
    dyaw = rng.uniform(-task.start_yaw_noise, task.start_yaw_noise)
    if start_noise:
        x, y, yaw = x + float(dx), y + float(dy), yaw + float(dyaw)
    robot = (x, y, yaw)
    if task.block_xy is not None:
        return Scene(robot, task.block_xy)
    start = np.array([x, y])
    half_fov = math.radians(horizontal_fov_deg() / 2)
    goal_bearing = half_fov - math.radians(task.goal_fov_margin_deg)

    def place(distance: float, bearing: float) -> np.ndarray:
        return start + distance * np.array([math.cos(yaw + bearing), math.sin(yaw + bearing)])

    goal = place(rng.uniform(*task.goal_distance), rng.uniform(-goal_bearing, goal_bearing))
    blocks = [goal]
    distractors: list[tuple[float, float, str]] = []
    count = int(rng.integers(task.distractors[0], task.distractors[1] + 1))
    for _ in range(count):
        for _attempt in range(200):
            where = place(rng.uniform(0.3, task.goal_distance[1] + 0.2),
                          rng.uniform(-half_fov, half_fov))
            color = str(rng.choice(("green", "blue")))
            if (_in_room(where)
                    and min(np.linalg.norm(where - b) for b in blocks) >= task.min_block_spacing
                    and _segment_distance(where, start, goal) >= task.path_clearance):
                blocks.append(where)
                distractors.append((float(where[0]), float(where[1]), color))
                break
    return Scene(robot, (float(goal[0]), float(goal[1])), tuple(distractors))


def outcome(task: Task, world: JetbotWorld) -> dict[str, Any]:
    """The task's success test on the world's current state, with the quantities it uses."""
    distance = world.distance_to_block()
    shift = world.block_shift()
    speed = world.robot_speed()
    success = distance < task.success_distance
    if task.stop_speed is not None:
        success = success and speed < task.stop_speed
    if task.max_block_shift is not None:
        success = success and shift < task.max_block_shift
    failed = task.max_block_shift is not None and shift >= task.max_block_shift
    return {"distance": distance, "block_shift": shift, "speed": speed,
            "is_success": bool(success), "failed": bool(failed)}
