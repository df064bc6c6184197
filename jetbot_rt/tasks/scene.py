"""Scene pieces: what a task puts in the room, and where. Plain data, no physics engine.

A task's ``scene(rng, start_noise)`` returns a ``Scene``: the robot's start pose and a tuple of
pieces, built by the simulator in that order (the order is part of a seeded episode: the same
pieces in the same order replay bit for bit). The room (a 3 m square with a checkered floor and
four walls, colours from ``[sim]``) is always there; pieces go on its floor.

Colours are a name of ``COLORS`` or an (r, g, b) triple in [0, 1]. A ``Block`` with colour
``None`` takes ``[sim] block_color`` (red unless randomized): the goal colour the appearance
randomization varies.

Give a piece a ``name`` to ask the world about it in ``Task.outcome`` (``world.distance(name)``,
``world.position(name)``, ``world.shift(name)``, ``world.touching(name)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Tuple, Union

from jetbot_rt.errors import UsageError

Color = Union[str, Tuple[float, float, float], None]
XY = Tuple[float, float]

COLORS: dict[str, tuple[float, float, float]] = {
    "red": (0.9, 0.05, 0.05),
    "green": (0.1, 0.65, 0.15),
    "blue": (0.1, 0.2, 0.9),
    "yellow": (0.9, 0.8, 0.1),
    "orange": (0.95, 0.45, 0.05),
    "white": (0.95, 0.95, 0.95),
    "black": (0.05, 0.05, 0.05),
    "grey": (0.5, 0.5, 0.5),
}
"""Named colours (RGB in [0, 1]); red, green and blue are the blocks' colours of the built-in
tasks' scenes."""

ROOM_HALF_SIZE = 1.5
"""m; the walls' inner faces stand at x, y = +-this."""
BLOCK_HALF_SIZE = 0.025
"""m; a ``Block`` is a 5 cm cube."""


def rgb(color: Color) -> tuple[float, float, float] | None:
    """``color`` as an RGB triple (None stays None); ``UsageError`` for an unknown name or a
    value out of [0, 1]."""
    if color is None:
        return None
    if isinstance(color, str):
        if color not in COLORS:
            raise UsageError(f"unknown colour {color!r} (known: {', '.join(sorted(COLORS))})")
        return COLORS[color]
    values = tuple(float(c) for c in color)
    if len(values) != 3 or not all(0.0 <= c <= 1.0 for c in values):
        raise UsageError(f"a colour is a name or 3 numbers in [0, 1], got {color!r}")
    return values  # type: ignore[return-value]


@dataclass(frozen=True)
class Block:
    """A movable 5 cm cube (0.2 kg) standing on the floor at ``xy``: a goal, a distractor."""

    xy: XY
    color: Color = None
    name: str = ""


@dataclass(frozen=True)
class Box:
    """A fixed box (an obstacle) centred at ``xy`` on the floor: ``size`` (x, y, z) in m,
    turned by ``yaw`` rad. The robot collides with it and cannot move it."""

    xy: XY
    size: tuple[float, float, float] = (0.1, 0.1, 0.1)
    color: Color = "grey"
    yaw: float = 0.0
    name: str = ""


@dataclass(frozen=True)
class Wall:
    """A fixed wall on the floor from ``start`` to ``end`` (m): a ``Box`` along that segment,
    ``height`` tall, ``thickness`` thick."""

    start: XY
    end: XY
    color: Color = "white"
    height: float = 0.2
    thickness: float = 0.02
    name: str = ""

    def as_box(self) -> Box:
        (x0, y0), (x1, y1) = self.start, self.end
        length = math.hypot(x1 - x0, y1 - y0)
        return Box(((x0 + x1) / 2, (y0 + y1) / 2), (length, self.thickness, self.height),
                   self.color, math.atan2(y1 - y0, x1 - x0), self.name)


@dataclass(frozen=True)
class Tape:
    """Tape on the floor along the polyline ``points`` (m), ``width`` wide: seen by the camera,
    never touched (no collision). ``closed`` joins the last point to the first (a track)."""

    points: tuple[XY, ...]
    width: float = 0.05
    color: Color = "black"
    closed: bool = False
    name: str = ""

    def segments(self) -> list[tuple[XY, XY]]:
        pts = list(self.points)
        if self.closed and len(pts) > 2:
            pts.append(pts[0])
        return list(zip(pts[:-1], pts[1:]))


Piece = Union[Block, Box, Wall, Tape]


@dataclass(frozen=True)
class Scene:
    """One episode's layout: the robot's start (x, y, yaw of its axle midpoint) and the pieces,
    built in this order. ``floor_color`` / ``wall_color``: the room's, over ``[sim]``'s
    (None: ``[sim]``'s, which randomization varies)."""

    robot_pose: tuple[float, float, float]
    pieces: tuple[Piece, ...] = ()
    floor_color: Color = None
    wall_color: Color = None

    def piece(self, name: str) -> Piece:
        """The piece called ``name``; ``KeyError`` if none is."""
        for piece in self.pieces:
            if piece.name == name:
                return piece
        raise KeyError(name)

    def has(self, name: str) -> bool:
        return any(piece.name == name for piece in self.pieces)
