"""The vision tasks ``follow`` (road following on a tape track) and ``avoid`` (collision
avoidance among random obstacles): their scenes, success tests and privileged experts."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from jetbot_rt.tasks import BUILTIN, Box, Tape, Wall, available, load_task
from jetbot_rt.tasks.avoid import RAY_ANGLES, ROBOT_RADIUS, Avoid, Rectangles, rectangles_of
from jetbot_rt.tasks.follow import MIN_TURN_RADIUS, TRACK, Follow, Track, luminance, min_turn_radius
from jetbot_rt.tasks.scene import ROOM_HALF_SIZE, Scene, rgb

pytest.importorskip("gymnasium")
pytest.importorskip("pybullet")

SEEDS = range(10_000, 10_004)


def run_episode(env: Any, seed: int, act: Any) -> dict[str, Any]:
    _, info = env.reset(seed=seed)
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(act(info))
        done = terminated or truncated
    return info


def successes(task: str, act: Any) -> int:
    from jetbot_rt.train.env import JetbotEnv
    from jetbot_rt.train.expert import EXPERT_FRAME

    env = JetbotEnv(task, image_size=EXPERT_FRAME)  # these drivers read the info, not pixels
    try:
        return sum(bool(run_episode(env, seed, act)["is_success"]) for seed in SEEDS)
    finally:
        env.close()


def test_follow_and_avoid_are_built_in_tasks_listed_with_the_others() -> None:
    assert {"follow", "avoid"} <= set(BUILTIN)
    assert {"follow", "avoid"} <= set(available())
    assert isinstance(load_task("follow"), Follow)
    assert isinstance(load_task("avoid"), Avoid)


@pytest.mark.parametrize("task", [Follow, Avoid])
def test_a_seed_draws_the_same_scene_every_time_and_start_noise_moves_only_the_robot(
        task: type) -> None:
    first = [task().scene(np.random.default_rng(seed), True) for seed in range(20)]
    again = [task().scene(np.random.default_rng(seed), True) for seed in range(20)]
    quiet = [task().scene(np.random.default_rng(seed), False) for seed in range(20)]
    assert first == again
    assert [s.pieces for s in first] == [s.pieces for s in quiet]
    assert len({s.pieces for s in first}) == 20  # every seed its own scene


def test_follow_tracks_stay_in_the_room_with_bends_the_robot_can_take_and_visible_tape() -> None:
    task = Follow()
    widths, radii = [], []
    for seed in range(40):
        scene = task.scene(np.random.default_rng(seed), False)
        tape = scene.piece(TRACK)
        assert isinstance(tape, Tape) and tape.closed
        points = np.array(tape.points)
        assert np.max(np.abs(points)) <= ROOM_HALF_SIZE - 0.3 + 1e-9
        radii.append(min_turn_radius(points))
        assert radii[-1] >= MIN_TURN_RADIUS
        assert abs(luminance(rgb(tape.color)) - luminance(rgb(scene.floor_color))) >= 0.25
        widths.append(tape.width)
        offset, _ = Track.of(points).nearest(np.array(scene.robot_pose[:2]))
        assert offset < 1e-9  # starts on the centre line
    assert max(widths) - min(widths) > 0.05  # width and curvature vary per episode
    assert max(radii) - min(radii) > 0.2


def test_avoid_obstacles_leave_room_to_pass_and_the_robot_starts_clear_of_them() -> None:
    task = Avoid()
    kinds = set()
    for seed in range(40):
        scene = task.scene(np.random.default_rng(seed), True)
        boxes = [p.as_box() if isinstance(p, Wall) else p for p in scene.pieces]
        assert all(isinstance(b, Box) for b in boxes)
        assert task.boxes[0] <= sum(isinstance(p, Box) for p in scene.pieces)
        kinds |= {(type(p).__name__, p.color) for p in scene.pieces}
        x, y, yaw = scene.robot_pose
        # No ray from the start meets an obstacle grown by the robot's radius sooner than the
        # start clearance allows (the grown rectangles' corners reach sqrt(2) radii out).
        ranges = rectangles_of(scene).ranges(x, y, yaw)
        assert np.min(ranges) >= task.start_clearance - math.sqrt(2) * ROBOT_RADIUS - 1e-6
    assert len({c for kind, c in kinds if kind == "Box"}) >= 5
    assert any(kind == "Wall" for kind, _ in kinds)


def test_the_avoid_rays_measure_the_free_distance_to_a_grown_box() -> None:
    scene = Scene((0.0, 0.0, 0.0), (Box((0.6, 0.0), (0.2, 0.2, 0.1)),))
    ranges = rectangles_of(scene).ranges(0.0, 0.0, 0.0)
    straight = ranges[len(ranges) // 2]
    assert straight == pytest.approx(0.6 - 0.1 - ROBOT_RADIUS)
    # Facing away, the nearest thing ahead is the room's wall, 1.5 m off, grown likewise.
    behind = rectangles_of(scene).ranges(0.0, 0.0, math.pi)
    assert behind[len(behind) // 2] == pytest.approx(min(1.0, ROOM_HALF_SIZE - ROBOT_RADIUS))
    inside = Rectangles(np.array([[0.0, 0.0]]), np.array([[0.2, 0.2]]), np.array([0.3]))
    assert np.all(inside.ranges(0.05, 0.0, 1.0) == 0.0)


class ClutterWorld:
    """A world view with one clutter piece (what ``JetbotWorld.clutter`` returns)."""

    def __init__(self, *pieces: Box) -> None:
        self.pieces = pieces

    def clutter(self) -> tuple[Box, ...]:
        return self.pieces


def test_the_avoid_rays_see_the_worlds_clutter_as_obstacles() -> None:
    scene = Scene((0.0, 0.0, 0.0), ())
    cabinet = Box((0.7, 0.0), (0.2, 0.4, 0.5))
    straight = len(RAY_ANGLES) // 2
    assert rectangles_of(scene).ranges(0.0, 0.0, 0.0)[straight] == pytest.approx(1.0)
    seen = rectangles_of(scene, ClutterWorld(cabinet)).ranges(0.0, 0.0, 0.0)
    assert seen[straight] == pytest.approx(0.7 - 0.1 - ROBOT_RADIUS)


def test_the_worlds_clutter_footprints_are_where_its_bodies_stand() -> None:
    from jetbot_rt.sim.config import SimConfig
    from jetbot_rt.sim.pybullet_import import import_pybullet
    from jetbot_rt.sim.world import JetbotWorld

    p = import_pybullet()
    scene = Avoid().scene(np.random.default_rng(5), True)
    world = JetbotWorld(SimConfig(clutter=6, look_seed=3), image_size=(8, 8))
    try:
        world.reset(scene=scene)
        footprints = world.clutter()
        assert len(footprints) >= 3
        bodies = world._bodies[len(scene.pieces):]  # the clutter's, built after the scene's
        assert len(bodies) == len(footprints)
        for box, body in zip(footprints, bodies):
            low, high = p.getAABB(body, physicsClientId=world._client)
            for corner in _corners(box):  # the footprint lies within the body's bounds
                assert low[0] - 1e-3 <= corner[0] <= high[0] + 1e-3
                assert low[1] - 1e-3 <= corner[1] <= high[1] + 1e-3
    finally:
        world.close()


def _corners(box: Box) -> np.ndarray:
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    hx, hy = box.size[0] / 2 * 0.99, box.size[1] / 2 * 0.99
    local = np.array([(hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)])
    return local @ np.array([[c, s], [-s, c]]) + np.array(box.xy)


def test_leaving_the_track_fails_the_episode_and_ends_it() -> None:
    from jetbot_rt.train.env import JetbotEnv

    env = JetbotEnv("follow")
    try:
        _, info = env.reset(seed=3, options={"robot_pose": (0.0, 0.0, 0.0)})  # the infield
        assert info["failed"] and not info["is_success"]
        _, info = env.reset(seed=3)
        assert not info["failed"] and info["offset"] < 0.05  # a new episode starts afresh
        _, _, terminated, _, info = env.step(np.array([-1.0, 1.0]))
        assert not terminated
    finally:
        env.close()


def test_the_follow_expert_stays_on_the_track_and_driving_straight_on_leaves_it() -> None:
    expert = Follow().expert()
    assert successes("follow", expert.label) >= len(SEEDS) - 1
    assert successes("follow", lambda info: np.ones(2)) <= 1


def test_the_avoid_expert_keeps_moving_without_touching_anything() -> None:
    expert = Avoid().expert()
    assert successes("avoid", expert.label) >= len(SEEDS) - 1
    assert successes("avoid", lambda info: np.ones(2)) <= 1


def test_circling_blind_near_the_start_does_not_pass_avoid() -> None:
    # What a policy trained on a path-length test answered a blank camera with: a tight left
    # circle, clear of everything near a start 0.4 m from all obstacles.
    assert successes("avoid", lambda info: np.array([0.27, 0.9])) == 0
