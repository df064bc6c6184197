"""Clutter: furniture-like boxes and cylinders along the room's walls that are no part of the
task (a sofa's side, a shelf, a bin, a plant pot), drawn from a seed. Plain data, no physics.

Every piece stands against a wall, at least 10 cm in every dimension and never a colour that
could pass for the goal (``textures.goal_like``), so it is never the goal's shape and colour;
it keeps ``CLEARANCE`` from every piece of the task's scene (blocks, boxes, walls, tape) and
``ROBOT_CLEARANCE`` from the robot's start, so a task's layout and its success test stay as
the task drew them. A place that breaks a rule is drawn again (at most ``ATTEMPTS`` times;
then that piece is left out), always from the same generator, so a seed replays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from jetbot_rt.sim.textures import home_color
from jetbot_rt.tasks.scene import ROOM_HALF_SIZE, Block, Box, Scene, Tape, Wall

CLEARANCE = 0.25
"""m between a clutter piece's footprint and any of the task's pieces."""
ROBOT_CLEARANCE = 0.4
"""m between a clutter piece's footprint and the robot's start."""
ATTEMPTS = 30


@dataclass(frozen=True)
class Furniture:
    """One clutter piece: ``kind`` "box" (``size`` = x, y, z, turned by ``yaw``) or
    "cylinder" (``size`` = radius, radius, height), standing on the floor at ``xy``."""

    kind: str
    xy: tuple[float, float]
    size: tuple[float, float, float]
    color: tuple[float, float, float]
    yaw: float = 0.0

    @property
    def radius(self) -> float:
        """m; of a circle around the footprint."""
        if self.kind == "cylinder":
            return self.size[0]
        return math.hypot(self.size[0], self.size[1]) / 2

    def footprint(self) -> Box:
        """The piece as a task's ``Box`` of its footprint (a cylinder as the square around
        it): what a task's geometry (``WorldView.clutter``) sees of it."""
        if self.kind == "cylinder":
            side = 2 * self.size[0]
            return Box(self.xy, (side, side, self.size[2]), "grey")
        return Box(self.xy, self.size, "grey", self.yaw)


def _scene_points(scene: Scene) -> list[tuple[np.ndarray, float]]:
    """Points of the task's pieces, each with how far the piece reaches around it (m)."""
    points: list[tuple[np.ndarray, float]] = []

    def along(start: tuple[float, float], end: tuple[float, float], reach: float) -> None:
        a, b = np.asarray(start, float), np.asarray(end, float)
        steps = max(1, int(np.linalg.norm(b - a) / 0.1))
        points.extend((a + (b - a) * t, reach) for t in np.linspace(0.0, 1.0, steps + 1))

    for piece in scene.pieces:
        if isinstance(piece, Block):
            points.append((np.asarray(piece.xy, float), 0.04))
        elif isinstance(piece, Box):
            points.append((np.asarray(piece.xy, float), math.hypot(*piece.size[:2]) / 2))
        elif isinstance(piece, Wall):
            along(piece.start, piece.end, piece.thickness / 2)
        elif isinstance(piece, Tape):
            for start, end in piece.segments():
                along(start, end, piece.width / 2)
    return points


def _one(rng: np.random.Generator) -> tuple[str, tuple[float, float, float], float]:
    """A piece's kind, size and depth from the wall (m)."""
    if rng.random() < 0.65:
        width, depth = rng.uniform(0.15, 0.9), rng.uniform(0.12, 0.45)
        return "box", (width, depth, rng.uniform(0.1, 0.7)), depth
    radius = rng.uniform(0.06, 0.2)
    return "cylinder", (radius, radius, rng.uniform(0.1, 0.6)), 2 * radius


def furniture(count: int, seed: int, scene: Scene) -> list[Furniture]:
    """``count`` clutter pieces for ``scene`` from ``seed`` (fewer when the room's edges have
    no place left that keeps the clearances)."""
    rng = np.random.default_rng([seed, 4])
    points = _scene_points(scene)
    robot = np.asarray(scene.robot_pose[:2], float)
    placed: list[Furniture] = []
    for _ in range(count):
        kind, size, depth = _one(rng)
        color = home_color(rng, None, (0.0, 0.8), (0.1, 0.95))
        for _attempt in range(ATTEMPTS):
            wall = int(rng.integers(4))  # +x, -x, +y, -y
            gap = rng.uniform(0.0, 0.06)
            reach = size[0] / 2 if kind == "box" else size[0]
            run = rng.uniform(-ROOM_HALF_SIZE + reach, ROOM_HALF_SIZE - reach)
            off = ROOM_HALF_SIZE - gap - depth / 2
            xy, yaw = {0: ((off, run), math.pi / 2), 1: ((-off, run), math.pi / 2),
                       2: ((run, off), 0.0), 3: ((run, -off), 0.0)}[wall]
            piece = Furniture(kind, (float(xy[0]), float(xy[1])), size, color,
                              yaw if kind == "box" else 0.0)
            where = np.asarray(piece.xy)
            if np.linalg.norm(where - robot) < piece.radius + ROBOT_CLEARANCE:
                continue
            if any(np.linalg.norm(where - p) < piece.radius + r + CLEARANCE for p, r in points):
                continue
            if any(np.linalg.norm(where - np.asarray(o.xy)) < piece.radius + o.radius
                   for o in placed):
                continue
            placed.append(piece)
            break
    return placed
