"""The PyBullet world: real physics and real rendering, no stand-ins."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jetbot_rt.sim.config import SimConfig
from jetbot_rt.sim.world import JetbotWorld

TICK = 1 / 30


@pytest.fixture
def world():
    w = JetbotWorld(SimConfig())
    yield w
    w.close()


def drive(world: JetbotWorld, left: float, right: float, seconds: float) -> None:
    world.set_duty(left, right)
    for _ in range(round(seconds / TICK)):
        world.step(TICK)


def red_mask(image: np.ndarray) -> np.ndarray:
    r, g, b = (image[:, :, i].astype(int) for i in range(3))
    return (r > 100) & (r > 2 * g) & (r > 2 * b)


def trajectory(world: JetbotWorld, duties) -> tuple[np.ndarray, np.ndarray]:
    poses = []
    for left, right in duties:
        world.set_duty(left, right)
        world.step(TICK)
        poses.append(world.robot_pose() + world.block_position())
    return np.array(poses), world.render()


DUTIES = [(0.1, 0.1)] * 30 + [(1.0, 1.0)] * 45 + [(-0.5, 0.5)] * 10  # hits the block, turns


def test_seed_scene(world):
    x, y, yaw = world.robot_pose()
    assert (x, y, yaw) == pytest.approx((-0.6, 0.0, 0.0), abs=1e-6)
    assert world.block_position() == pytest.approx((0.3, 0.0, 0.025), abs=1e-6)
    assert world.distance_to_block() == pytest.approx(0.9, abs=0.01)
    assert world.sim_time == 0.0


def test_same_inputs_give_the_same_trajectory_and_images(world):
    first, first_image = trajectory(world, DUTIES)
    other = JetbotWorld(SimConfig())  # a second world in the same process
    try:
        second, second_image = trajectory(other, DUTIES)
    finally:
        other.close()
    world.reset()  # a reset world replays like a new one, even after the block was hit
    third, third_image = trajectory(world, DUTIES)
    assert first[-1, 3] > 0.35  # the robot pushed the block: contacts are replayed too
    assert np.array_equal(first, second) and np.array_equal(first, third)
    assert np.array_equal(first_image, second_image) and np.array_equal(first_image, third_image)


def test_worlds_are_independent():
    a, b = JetbotWorld(SimConfig()), JetbotWorld(SimConfig())
    try:
        drive(a, 0.5, 0.5, 1.0)
        assert a.robot_pose()[0] > -0.5
        assert b.robot_pose() == pytest.approx((-0.6, 0.0, 0.0), abs=1e-6)
        assert b.sim_time == 0.0
    finally:
        a.close()
        b.close()


def test_forward_duty_drives_toward_the_block(world):
    start = world.distance_to_block()
    drive(world, 0.1, 0.1, 3.0)
    x, y, yaw = world.robot_pose()
    # duty 0.1 * gain 20 rad/s * radius 0.03 m = 0.06 m/s; 3 s minus the motor lag
    assert 0.15 < x + 0.6 < 0.2
    assert abs(y) < 0.005 and abs(yaw) < 0.01
    assert start - world.distance_to_block() == pytest.approx(x + 0.6, abs=0.005)


def test_opposite_duties_turn_in_place(world):
    drive(world, 0.1, -0.1, 2.0)
    x, y, yaw = world.robot_pose()
    # right wheel backwards: clockwise; 2 * 0.06 m/s / 0.11 m track = 1.09 rad/s
    assert -2.4 < yaw < -1.9
    assert math.hypot(x + 0.6, y) < 0.01


def test_reset_places_robot_and_block(world):
    drive(world, 0.5, 0.5, 0.5)
    world.reset(robot_pose=(0.5, -0.4, math.pi / 2), block_xy=(-0.2, 0.7))
    assert world.robot_pose() == pytest.approx((0.5, -0.4, math.pi / 2), abs=1e-6)
    assert world.block_position()[:2] == pytest.approx((-0.2, 0.7), abs=1e-6)
    assert world.sim_time == 0.0 and world.duty == (0.0, 0.0)
    assert world.wheel_velocities() == pytest.approx((0.0, 0.0), abs=1e-9)


@pytest.mark.parametrize("tau", [0.05, 0.2])
def test_motor_velocity_follows_a_first_order_lag(tau):
    sim = SimConfig(motor_tau=tau)
    world = JetbotWorld(sim)
    try:
        world.set_duty(0.3, 0.3)
        target = 0.3 * sim.motor_gain
        world.step(tau)
        after_one_tau = world.wheel_velocities()
        world.step(4 * tau)
        after_five_tau = world.wheel_velocities()
    finally:
        world.close()
    for v in after_one_tau:
        assert v / target == pytest.approx(1 - math.exp(-1), abs=0.05)
    for v in after_five_tau:
        assert v / target == pytest.approx(1.0, abs=0.03)


def test_without_lag_the_wheel_reaches_its_target_at_once():
    world = JetbotWorld(SimConfig(motor_tau=0.0))
    try:
        world.set_duty(0.3, -0.3)
        world.step(0.05)  # with the default tau of 0.05 s this would be 63 % of the target
        assert world.wheel_velocities() == pytest.approx((6.0, -6.0), abs=0.15)
    finally:
        world.close()


def test_steps_are_whole_physics_substeps(world):
    h = 1 / SimConfig().physics_hz
    for _ in range(30):
        world.step(TICK)
    assert world.sim_time == pytest.approx(1.0, abs=1e-12)
    world.step(0.4 * h)  # less than half a sub-step: carried, not run
    assert world.sim_time == pytest.approx(1.0, abs=1e-12)
    world.step(0.2 * h)
    assert world.sim_time == pytest.approx(1.0 + h, abs=1e-12)


def _poses(physics_hz: float, duties) -> np.ndarray:
    world = JetbotWorld(SimConfig(physics_hz=physics_hz), image_size=(8, 8))
    try:
        return trajectory(world, duties)[0][:, :3]
    finally:
        world.close()


def test_the_default_sub_steps_keep_the_trajectories_of_twice_as_many():
    """120 Hz (4 sub-steps a tick) against 240 Hz, the same duties for 10 s: policy-like
    driving stays within 1 cm and 1.5 deg; a sustained curve, where wheel-floor contact is
    most sensitive to the step, turns within 5 % of the same angle (docs/SIM.md, "Physics
    sub-steps", has the measurements and why not 60 Hz)."""
    assert SimConfig().physics_hz == 120
    rng = np.random.default_rng(0)
    policy_like = np.clip(0.07 + 0.05 * rng.standard_normal((300, 2)), -0.1, 0.1)
    for duties in ([(0.1, 0.1)] * 300, policy_like):
        fine, default = _poses(240, duties), _poses(120, duties)
        assert np.abs(default[:, :2] - fine[:, :2]).max() < 0.01
        assert np.degrees(np.abs(default[:, 2] - fine[:, 2]).max()) < 1.5
    curve = [(0.1, 0.05)] * 300
    fine, default = _poses(240, curve), _poses(120, curve)
    turned_fine = np.unwrap(fine[:, 2])[-1] - fine[0, 2]
    turned = np.unwrap(default[:, 2])[-1] - default[0, 2]
    assert abs(turned_fine) > 2.0 and turned / turned_fine == pytest.approx(1.0, abs=0.05)


def test_duties_are_clipped_and_must_be_finite(world):
    world.set_duty(1.7, -3.0)
    assert world.duty == (1.0, -1.0)
    with pytest.raises(ValueError):
        world.set_duty(float("nan"), 0.0)
    with pytest.raises(ValueError):
        world.step(-0.1)


def test_camera_sees_the_red_block_ahead(world):
    image = world.render()
    assert image.shape == (224, 224, 3) and image.dtype == np.uint8
    red = red_mask(image)
    rows, cols = np.nonzero(red)
    assert 20 < red.sum() < 400  # a 5 cm cube 0.9 m away
    assert abs(cols.mean() - 111.5) < 6
    assert rows.mean() < 112  # above the image centre: the camera is pitched down
    drive(world, 0.1, 0.1, 5.0)
    closer = red_mask(world.render())
    assert closer.sum() > 2 * red.sum()  # 0.84 m -> 0.54 m from the camera: ~2.4x the area
    assert abs(np.nonzero(closer)[1].mean() - 111.5) < 6


def test_block_leaves_the_view_when_the_robot_turns_away(world):
    world.reset(robot_pose=(-0.6, 0.0, math.pi / 2))
    assert red_mask(world.render()).sum() == 0


def test_image_size_is_width_by_height():
    world = JetbotWorld(SimConfig(), image_size=(160, 120))
    try:
        assert world.render().shape == (120, 160, 3)
    finally:
        world.close()


def test_close_is_idempotent():
    world = JetbotWorld(SimConfig())
    world.close()
    world.close()
