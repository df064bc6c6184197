"""Each [sim] imperfection on the real PyBullet world: it changes what it should and nothing
else. A dynamics knob moves the robot differently and leaves the pixels of a given pose alone;
a camera or appearance knob changes pixels and leaves the trajectory bit for bit alone."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from jetbot_rt.sim.config import SimConfig

pytest.importorskip("pybullet")

from jetbot_rt.sim.probes import SIZE, TICK, drive_straight, wall_push
from jetbot_rt.sim.world import JetbotWorld, pixel_centred

SUBSTEP = 1 / 240
DUTIES = [(0.3, 0.3)] * 12 + [(0.3, -0.2)] * 6  # drives, then turns: the view moves


PINHOLE = SimConfig(lens="pinhole")
"""The ideal [sim] through the pinhole: these tests read the renderer's own projection (the
fisheye's warp of it: tests/test_lens.py)."""


def sim(**changes) -> SimConfig:
    return dataclasses.replace(PINHOLE, **changes)


def run(config: SimConfig, duties=DUTIES, camera: str = "frame"):
    """Poses and the camera's frames over ``duties``, one control tick each."""
    world = JetbotWorld(config, image_size=SIZE)
    try:
        poses, frames = [], [getattr(world, camera)()]
        for left, right in duties:
            world.set_duty(left, right)
            world.step(TICK)
            poses.append(world.robot_pose())
            frames.append(getattr(world, camera)())
        return np.array(poses), np.array(frames)
    finally:
        world.close()


@pytest.fixture(scope="module")
def ideal():
    return run(PINHOLE)


# --- dynamics -----------------------------------------------------------------------------

def test_weak_right_wheel_curves_right_at_the_kinematic_rate():
    poses = drive_straight(sim(wheel_gain=[1.0, 0.85]), 0.3, 2.0)
    yaw = np.unwrap(poses[:, 2])
    rate = (yaw[-1] - yaw[15]) / ((len(yaw) - 16) * TICK)  # after the motor lag
    # wheel speeds 20 * 0.3 * (1, 0.85) rad/s * 0.03 m over the 0.11 m track
    expected = 20 * 0.3 * 0.03 * (0.85 - 1.0) / 0.11
    assert rate == pytest.approx(expected, rel=0.05)  # -0.245 rad/s: clockwise, to the right
    assert drive_straight(SimConfig(), 0.3, 2.0)[-1, 2] == pytest.approx(0.0, abs=0.005)


def test_deadband_above_the_duty_keeps_the_robot_still():
    still = drive_straight(sim(deadband=0.12), 0.1, 2.0)
    resting = drive_straight(SimConfig(), 0.0, 2.0)
    assert np.abs(still - resting).max() < 1e-4  # as if no duty were written
    # above the dead-band the speed is motor_gain * (duty - deadband): 20 * 0.05 * 0.03 m/s
    slow = drive_straight(sim(deadband=0.05), 0.1, 2.0)
    speed = (slow[-1, 0] - slow[15, 0]) / ((len(slow) - 16) * TICK)
    assert speed == pytest.approx(0.03, rel=0.08)


def test_a_duty_lifted_by_the_deadband_drives_as_on_a_motor_without_one():
    from jetbot_rt.runtime.actions import ActionPipeline

    duty = ActionPipeline(max_speed=0.5, deadband=0.12).duties((0.2, 0.2))[0]  # 0.1 + 0.12
    lifted = drive_straight(sim(deadband=0.12), duty, 2.0)
    ideal = drive_straight(SimConfig(), 0.1, 2.0)
    assert np.abs(lifted - ideal).max() < 1e-3
    assert ideal[-1, 0] - ideal[0, 0] > 0.05  # it did drive (0.03 m/s for 2 s)


def _first_motion(config: SimConfig) -> float:
    world = JetbotWorld(config, image_size=SIZE)
    try:
        world.set_duty(0.5, 0.5)
        while world.sim_time < 0.5:
            world.step(SUBSTEP)
            if min(world.wheel_velocities()) > 0.05:
                return world.sim_time
        raise AssertionError("the wheels never turned")
    finally:
        world.close()


@pytest.mark.parametrize("latency", [0.05, 0.1])
def test_command_latency_delays_the_first_motion_by_that_time(latency):
    delay = _first_motion(sim(latency=latency)) - _first_motion(SimConfig())
    assert delay == pytest.approx(latency, abs=SUBSTEP / 2)


def _wall_push(config: SimConfig, duty: float) -> tuple[float, float]:
    """The mean force (N) against the wall over the probe's ticks, and the wheel's speed."""
    forces, spin = wall_push(config, duty)
    return float(np.mean(forces)), spin


def test_stall_torque_makes_torque_scale_with_duty():
    """With ``stall_torque`` the wheels' torque at standstill is stall * duty (a PWM-driven DC
    motor): pushing a wall, the force triples from duty 0.2 to 0.6 and the wheels stall.
    The ideal motor pushes with its constant 0.15 N m until the tyres slip."""
    dc = sim(stall_torque=0.078)
    (low, low_spin), (high, high_spin) = _wall_push(dc, 0.2), _wall_push(dc, 0.6)
    assert max(low_spin, high_spin) < 0.05
    assert 2.4 < high / low < 4.5
    nominal = 2 * 0.078 * 0.6 / 0.03  # two wheels' torque over the wheel radius
    assert 0.5 * nominal < high < 1.1 * nominal
    ideal_force, ideal_spin = _wall_push(SimConfig(), 0.2)
    assert ideal_force > 1.5 * high and ideal_spin > 1.0
    # the gentler start at a low duty; free running, the same speed as the ideal motor
    ideal = drive_straight(SimConfig(), 0.1, 2.0)
    slow = drive_straight(dc, 0.1, 2.0)
    assert slow[3, 0] - slow[0, 0] < 0.6 * (ideal[3, 0] - ideal[0, 0])  # after 0.1 s
    speeds = [(x[-1, 0] - x[30, 0]) / ((len(x) - 31) * TICK) for x in (ideal, slow)]
    assert speeds[1] == pytest.approx(speeds[0], rel=0.05)


def test_dynamics_knobs_leave_the_pixels_of_a_pose_alone():
    a = JetbotWorld(PINHOLE, image_size=SIZE)
    b = JetbotWorld(sim(wheel_gain=[0.9, 1.1], deadband=0.05, latency=0.05, stall_torque=0.08),
                    image_size=SIZE)
    try:
        assert np.array_equal(a.frame(), b.frame())
    finally:
        a.close()
        b.close()


# --- camera -------------------------------------------------------------------------------

@pytest.mark.parametrize("latency, substeps", [(0.1, 24), (0.05, 12)])
def test_camera_latency_shows_the_world_that_long_ago(ideal, latency, substeps):
    poses, frames = run(sim(camera_latency=latency))
    assert np.array_equal(poses, ideal[0])  # the robot moves exactly as before
    world = JetbotWorld(PINHOLE, image_size=SIZE)  # the ideal camera, sub-step by sub-step
    try:
        shown = {0: world.render()}
        for left, right in DUTIES:
            world.set_duty(left, right)
            for _ in range(8):
                world.step(SUBSTEP)
                shown[round(world.sim_time * 240)] = world.render()
    finally:
        world.close()
    for k, frame in enumerate(frames):
        assert np.array_equal(frame, shown[max(8 * k - substeps, 0)])
    assert not np.array_equal(frames[-1], ideal[1][-1])


def test_camera_mount_moves_the_view_and_nothing_else(ideal):
    def red_rows(frame):
        r, g, b = (frame[:, :, i].astype(int) for i in range(3))
        rows = np.nonzero((r > 100) & (r > 2 * g) & (r > 2 * b))[0]
        return rows.mean(), rows.size

    row0, area0 = red_rows(ideal[1][0])
    for changes, check in [
        ({"camera_pitch_deg": 30.0}, lambda row, area: row < row0 - 3),  # tilted down more
        ({"camera_height": 0.2}, lambda row, area: row > row0 + 2),  # looks down on it
        ({"camera_vfov_deg": 70.0}, lambda row, area: area < 0.8 * area0),  # wider, smaller
    ]:
        poses, frames = run(sim(**changes))
        assert np.array_equal(poses, ideal[0]), changes
        assert check(*red_rows(frames[0])), changes


@pytest.mark.parametrize("changes", [
    {"floor_color": [0.3, 0.5, 0.3]},
    {"floor_texture": "plain"},
    {"wall_color": [0.9, 0.9, 0.9]},
    {"block_color": [0.1, 0.1, 0.9]},
    {"light_direction": [1.0, -1.0, 0.3]},
    {"light_intensity": 0.6},
    {"image_brightness": 0.1},
    {"image_contrast": 0.7},
    {"image_blur": 0.02},
    {"image_noise": 0.03},
])
def test_appearance_changes_pixels_not_dynamics(ideal, changes):
    poses, frames = run(sim(**changes))
    assert np.array_equal(poses, ideal[0])
    assert (frames != ideal[1]).any(axis=-1).sum() > 50


def test_appearance_does_what_it_says(ideal):
    frame0 = ideal[1][0].astype(float)
    bright = run(sim(image_brightness=0.1), duties=[])[1][0].astype(float)
    assert (bright - frame0).mean() == pytest.approx(25.5, abs=2.0)  # below the 255 clip
    flat = run(sim(image_contrast=0.5), duties=[])[1][0].astype(float)
    assert flat.std() == pytest.approx(0.5 * frame0.std(), rel=0.05)
    noisy = run(sim(image_noise=0.02), duties=[])[1][0].astype(float)
    assert (noisy - frame0).std() == pytest.approx(0.02 * 255, rel=0.1)
    blurred = run(sim(image_blur=0.02), duties=[])[1][0].astype(float)
    assert np.abs(np.diff(blurred, axis=1)).mean() < 0.8 * np.abs(np.diff(frame0, axis=1)).mean()
    dim = run(sim(light_intensity=0.5), duties=[])[1][0].astype(float)
    assert dim.mean() < 0.6 * frame0.mean()
    blue = run(sim(block_color=[0.05, 0.05, 0.9]), duties=[])[1][0].astype(int)
    r, g, b = (blue[:, :, i] for i in range(3))
    assert ((b > 100) & (b > 2 * r) & (b > 2 * g)).sum() > 5
    assert ((r > 100) & (r > 2 * g) & (r > 2 * b)).sum() == 0


def test_a_noisy_camera_replays_with_its_seed():
    a = run(sim(image_noise=0.05, seed=1), duties=DUTIES[:3])[1]
    b = run(sim(image_noise=0.05, seed=1), duties=DUTIES[:3])[1]
    c = run(sim(image_noise=0.05, seed=2), duties=DUTIES[:3])[1]
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_defaults_render_like_the_urdf_scene():
    """The ideal [sim] values are today's scene: the frame is the plain render (no colour
    set, PyBullet's default light, the URDF's camera mount)."""
    import pybullet as p

    world = JetbotWorld(PINHOLE, image_size=SIZE)
    try:
        c = world._client
        state = p.getLinkState(world._robot, 3, computeForwardKinematics=True,
                               physicsClientId=c)
        rotation = np.array(p.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        eye = np.array(state[4])
        view = p.computeViewMatrix(eye.tolist(), (eye + rotation[:, 0]).tolist(),
                                   rotation[:, 2].tolist(), physicsClientId=c)
        projection = pixel_centred(
            p.computeProjectionMatrixFOV(52.0, 16 / 9, 0.01, 5.0, physicsClientId=c), SIZE)
        rgba = p.getCameraImage(*SIZE, view, projection, shadow=0,
                                renderer=p.ER_TINY_RENDERER, physicsClientId=c)[2]
        plain = np.asarray(rgba, np.uint8).reshape(SIZE[1], SIZE[0], 4)[:, :, :3]
        assert np.array_equal(world.frame(), plain)
        assert math.isclose(world.sim.camera_pitch_deg, 20.0)
    finally:
        world.close()
