"""Physics probes of the simulated robot, shared by tests/test_sim_imperfections.py and
benchmarks/bench_sim_facts.py (which must not import the tests): a straight drive's poses and
the robot's push against a wall."""

from __future__ import annotations

import numpy as np

from jetbot_rt.sim.config import SimConfig
from jetbot_rt.sim.pybullet_import import import_pybullet
from jetbot_rt.sim.world import JetbotWorld

TICK = 1 / 30
"""The control loop's period: the probes step the world as the loop does."""
SIZE = (64, 64)
"""The worlds' image size (nothing here renders)."""


def drive_straight(config: SimConfig, duty: float, seconds: float,
                   pose: tuple[float, float, float] | None = None,
                   block_xy: tuple[float, float] = (0.3, 0.0)) -> np.ndarray:
    """The robot's (x, y, yaw) at the start and after each tick at ``duty`` on both wheels;
    from the world's own start, or from ``pose`` (with the block at ``block_xy``)."""
    world = JetbotWorld(config, image_size=SIZE)
    try:
        if pose is not None:
            world.reset(robot_pose=pose, block_xy=block_xy)
        world.set_duty(duty, duty)
        poses = [world.robot_pose()]
        for _ in range(round(seconds / TICK)):
            world.step(TICK)
            poses.append(world.robot_pose())
        return np.array(poses)
    finally:
        world.close()


def wall_push(config: SimConfig, duty: float) -> tuple[list[float], float]:
    """The robot's force (N) against the +x wall at each tick of the second half of 1 s at
    ``duty``, started 4 cm from it (a slipping wheel's push jumps from one tick to the next),
    and the fastest wheel's speed (rad/s) at the end."""
    p = import_pybullet()
    world = JetbotWorld(config, image_size=SIZE)
    try:
        world.reset(robot_pose=(1.4, 0.0, 0.0), block_xy=(-1.0, 1.0))
        world.set_duty(duty, duty)
        world.step(0.5)
        forces = []
        for _ in range(15):
            world.step(TICK)
            contacts = p.getContactPoints(world._robot, 0, physicsClientId=world._client)
            forces.append(-sum(c[9] * c[7][0] for c in contacts))  # normal force along -x
        return forces, max(abs(v) for v in world.wheel_velocities())
    finally:
        world.close()
