"""A printed checkerboard held in front of the simulated camera, for ``jetbot-rt calibrate
--camera --backend sim`` (the proof that the lens's intrinsics are recovered).

The page (``jetbot_rt/data/checkerboard-9x6.png``) is a textured quad posed in the camera's
frame, as a person holds a board in front of the robot: ahead, off to a side, tilted. Each view
replaces the previous page. ``board_views`` is the sequence the command shows the camera.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from jetbot_rt.calibration.intrinsics import BOARD_INNER, BOARD_SQUARE, Lens, board_png
from jetbot_rt.sim.camera_model import CAMERA_ASPECT
from jetbot_rt.sim.pybullet_import import import_pybullet
from jetbot_rt.sim.world import JetbotWorld

p = import_pybullet()

if TYPE_CHECKING:
    from jetbot_rt.sim.config import SimConfig

PAGE_SQUARES = (BOARD_INNER[0] + 2, BOARD_INNER[1] + 2)
"""The PNG's size in squares: the 10 x 7 board and half a square of white on every side."""


@dataclass(frozen=True)
class BoardPose:
    """Where the board's centre is from the camera (m: ahead, to the right, up) and how it
    is turned (degrees: about the vertical, about its own horizontal, in its plane)."""

    ahead: float
    right: float = 0.0
    up: float = 0.0
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0


def board_views(count: int = 15, field_deg: tuple[float, float] = (50.0, 28.0)) -> list[BoardPose]:
    """``count`` poses spread over the frame (centre, sides, corners), near and far, tilted
    both ways: what a person does with the board in front of the camera, watching where the
    frame's edges are (``field_deg``: the angles from the axis to the frame's side and top
    edges; the datasheet lens's by default). Deterministic."""
    rng = np.random.default_rng(20)
    spots = [(0.0, 0.0), (-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, 1), (-1, 1), (1, -1),
             (-0.5, 0.5), (0.5, -0.5), (-0.5, -0.5), (0.5, 0.5)]
    views = []
    for i in range(count):
        sx, sy = spots[i % len(spots)]
        ahead = float(rng.uniform(0.33, 0.45))
        # out to the frame's edges, where the distortion is (the board's centre 10 and 12
        # degrees inside them): some of these views leave the frame and are dropped
        right = sx * ahead * math.tan(math.radians(field_deg[0] - 10)) - sx * 0.04
        up = sy * ahead * math.tan(math.radians(field_deg[1] - 12))
        views.append(BoardPose(ahead, right, up, float(rng.uniform(-30, 30)) - 15 * sx,
                               float(rng.uniform(-25, 25)), float(rng.uniform(-15, 15))))
    return views


def show_board(world: JetbotWorld, pose: BoardPose, square: float = BOARD_SQUARE,
               previous: int | None = None) -> int:
    """Put the page at ``pose`` in front of ``world``'s camera (removing body ``previous``);
    the new body's id."""
    client = world.client
    if previous is not None:
        p.removeBody(previous, physicsClientId=client)
    eye, cam = world.camera_pose()  # columns: forward, left, up
    forward, left, up = cam[:, 0], cam[:, 1], cam[:, 2]
    yaw, pitch, roll = (math.radians(v) for v in (pose.yaw_deg, pose.pitch_deg, pose.roll_deg))
    # the page's axes facing the camera: across (the camera's right), up, and its normal
    across, upward = -left, up
    across, normal = _turn(across, -forward, up, yaw)
    upward, normal = _turn(upward, normal, across, pitch)
    across, upward = _turn(across, upward, normal, roll)
    half_w, half_h = PAGE_SQUARES[0] * square / 2, PAGE_SQUARES[1] * square / 2
    corners = [(-half_w, -half_h), (half_w, -half_h), (half_w, half_h), (-half_w, half_h)]
    vertices = [(across * u + upward * v).tolist() for u, v in corners]
    visual = p.createVisualShape(
        p.GEOM_MESH, vertices=vertices, indices=[0, 1, 2, 0, 2, 3, 0, 2, 1, 0, 3, 2],
        uvs=[[0, 0], [1, 0], [1, 1], [0, 1]], normals=[normal.tolist()] * 4,
        physicsClientId=client)
    centre = eye + forward * pose.ahead - left * pose.right + up * pose.up
    body = p.createMultiBody(0, -1, visual, centre.tolist(), physicsClientId=client)
    texture = p.loadTexture(str(board_png()), physicsClientId=client)
    p.changeVisualShape(body, -1, textureUniqueId=texture, rgbaColor=(1, 1, 1, 1),
                        physicsClientId=client)
    return body


def _turn(a: np.ndarray, b: np.ndarray, axis: np.ndarray,
          angle: float) -> tuple[np.ndarray, np.ndarray]:
    """``a`` and ``b`` (orthogonal to ``axis``) turned by ``angle`` about it."""
    c, s = math.cos(angle), math.sin(angle)
    return a * c + b * s, b * c - a * s


def field_angles(sim: SimConfig, size: tuple[int, int]) -> tuple[float, float]:
    """Degrees from the optical axis to the frame's side edge and to its top edge."""
    width, height = size
    if sim.lens != "fisheye":
        half_v = math.radians(sim.camera_vfov_deg) / 2
        return (math.degrees(math.atan(CAMERA_ASPECT * math.tan(half_v))), math.degrees(half_v))
    lens = Lens.from_sim(sim)
    matrix = lens.matrix(width, height)
    edges = np.array([width / 2 / matrix[0, 0], height / 2 / matrix[1, 1]])
    return tuple(float(math.degrees(a)) for a in lens.undistort_angle(edges, width, height))


def sim_views(sim: SimConfig, size: tuple[int, int], count: int) -> list[np.ndarray]:
    """The board at each of ``board_views(count)`` through ``[sim]``'s lens, rendered at
    ``size`` (the camera's ideal render: no latency, no sensor effects). The robot's camera is
    lifted and levelled first, so that the board is in the air and clear of the floor: the
    lens's intrinsics do not depend on the mount."""
    mount = dataclasses.replace(sim, camera_height=0.4, camera_pitch_deg=0.0)
    world = JetbotWorld(mount, image_size=size)
    try:
        body = None
        images = []
        for pose in board_views(count, field_angles(sim, size)):
            body = show_board(world, pose, previous=body)
            images.append(world.render())
        return images
    finally:
        world.close()
