"""The room's appearance families in a world: textured floor and walls, baked lamp and
window light, and clutter along the walls, built from ``[sim]`` for every task's scene.

At the defaults (``floor_texture`` "checker" or "plain", ``wall_texture`` "flat", no
skirting, lamps, window light or clutter) nothing here runs: the room is room.urdf coloured by
``appearance.apply_colors``, pixel for pixel as before. Otherwise the room is
room_textured.urdf and its floor and four walls get textures drawn by ``sim/textures.py`` from
``[sim] look_seed`` (written as BMP files to a private temporary directory and loaded with
``loadTexture``; PyBullet takes textures from files only). Clutter is ``sim/clutter.py``'s,
built as fixed bodies: the robot collides with it, and ``world.touching()`` counts it.
"""

from __future__ import annotations

import atexit
import math
import os
import shutil
import tempfile
from typing import TYPE_CHECKING

import cv2
import numpy as np

from jetbot_rt.sim import textures
from jetbot_rt.sim.appearance import AMBIENT, DIFFUSE, wall_colors
from jetbot_rt.sim.clutter import Furniture, furniture
from jetbot_rt.sim.pybullet_import import import_pybullet
from jetbot_rt.tasks.scene import Box, Scene, Wall

if TYPE_CHECKING:
    from jetbot_rt.sim.config import SimConfig

p = import_pybullet()

PLAIN_ROOM, TEXTURED_ROOM = "room.urdf", "room_textured.urdf"
_DIR: list[str] = []
_COUNT = [0]


def textured(sim: SimConfig) -> bool:
    """Whether ``sim`` asks for the textured room (any family beyond the checker and plain
    floors and flat walls, painted-on light, or shadows)."""
    return (sim.floor_texture not in ("checker", "plain") or sim.wall_texture != "flat"
            or sim.skirting_color is not None or sim.lamps > 0 or sim.window_light > 0
            or sim.shadows)


def room_urdf(sim: SimConfig) -> str:
    return TEXTURED_ROOM if textured(sim) else PLAIN_ROOM


def _remove(path: str, owner: int) -> None:
    """Remove the directory at exit, in the process that made it only (a forked child
    inherits the registration and would remove its parent's directory)."""
    if os.getpid() == owner:
        shutil.rmtree(path, ignore_errors=True)


def _texture_dir() -> str:
    """This process's private directory for texture files (0700, removed at exit; its
    files are only ever ours, written and then read back by PyBullet)."""
    if not _DIR:
        # memory-backed where there is one: a BMP on a disk-backed /tmp took 4 ms to write
        shm = "/dev/shm"
        where = shm if os.path.isdir(shm) and os.access(shm, os.W_OK) else None
        path = tempfile.mkdtemp(prefix="jetbot_rt-textures-", dir=where)
        atexit.register(_remove, path, os.getpid())
        _DIR.append(path)
    return _DIR[0]


def _load(client: int, name: str, image_rgb) -> int:  # type: ignore[no-untyped-def]
    """A texture id for ``image_rgb`` (row 0 is the texture's v = 0 edge: PyBullet's loader
    flips nothing, so the image is written upside down)."""
    # a new name every time: PyBullet keeps a loaded file's texture by its name and would
    # hand the first episode's back; the file goes once loaded (the texture is in memory)
    _COUNT[0] += 1
    path = os.path.join(_texture_dir(), f"{os.getpid()}-{client}-{_COUNT[0]}-{name}.bmp")
    if not cv2.imwrite(path, np.ascontiguousarray(image_rgb[::-1, :, ::-1])):
        raise OSError(f"cannot write the texture {path}")
    try:
        texture = p.loadTexture(path, physicsClientId=client)
    finally:
        os.unlink(path)
    if texture < 0:
        raise OSError(f"PyBullet could not load the texture {path}")
    return texture


def floor_image(sim: SimConfig):  # type: ignore[no-untyped-def]
    """The floor texture ``sim`` draws (family, colour, baked light), rows along +y."""
    base = tuple(sim.floor_color)
    image = textures.floor_texture(sim.floor_texture, base, sim.look_seed)  # type: ignore[arg-type]
    return textures.bake_light(image, sim.lamps, sim.window_light, sim.look_seed)


def wall_images(sim: SimConfig) -> list:  # type: ignore[type-arg]
    """The four walls' textures (+x, -x, +y, -y), top row first."""
    skirting = tuple(sim.skirting_color) if sim.skirting_color is not None else None
    return [textures.wall_texture(sim.wall_texture, rgb, skirting,  # type: ignore[arg-type]
                                  sim.look_seed + 7919 * i)
            for i, rgb in enumerate(wall_colors(sim))]


def dress_room(client: int, room: int, sim: SimConfig,
               shadows: list[np.ndarray] | None = None) -> None:
    """Texture the textured room's floor (visual 0, with ``shadows`` baked in) and walls
    (visuals 1..4)."""
    white = (1.0, 1.0, 1.0, 1.0)
    image = textures.bake_shadows(floor_image(sim), shadows or [], shadow_darkness(sim))
    floor = _load(client, "floor", image)
    p.changeVisualShape(room, -1, shapeIndex=0, textureUniqueId=floor, rgbaColor=white,
                        physicsClientId=client)
    if sim.wall_texture == "flat" and sim.skirting_color is None:  # colours, no texture
        for i, rgb in enumerate(wall_colors(sim)):
            p.changeVisualShape(room, -1, shapeIndex=1 + i, rgbaColor=(*rgb, 1.0),
                                physicsClientId=client)
        return
    for i, image in enumerate(wall_images(sim)):
        wall = _load(client, f"wall{i}", image[::-1])  # the wall mesh's v runs upwards
        p.changeVisualShape(room, -1, shapeIndex=1 + i, textureUniqueId=wall, rgbaColor=white,
                            physicsClientId=client)


def build_furniture(client: int, piece: Furniture) -> int:
    color = (*piece.color, 1.0)
    if piece.kind == "cylinder":
        radius, _, height = piece.size
        shape = p.createCollisionShape(p.GEOM_CYLINDER, radius=radius, height=height,
                                       physicsClientId=client)
        look = p.createVisualShape(p.GEOM_CYLINDER, radius=radius, length=height,
                                   rgbaColor=color, physicsClientId=client)
    else:
        half = [s / 2 for s in piece.size]
        height = piece.size[2]
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=client)
        look = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=color,
                                   physicsClientId=client)
    return p.createMultiBody(0.0, shape, look, (piece.xy[0], piece.xy[1], height / 2),
                             p.getQuaternionFromEuler((0.0, 0.0, piece.yaw)),
                             physicsClientId=client)


def _footprint(xy: tuple[float, float], size: tuple[float, float, float], yaw: float
               ) -> np.ndarray:
    """The four floor corners (m) of a box ``size`` at ``xy`` turned by ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    half = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * np.asarray(size[:2]) / 2
    return half @ np.array([[c, s], [-s, c]]) + np.asarray(xy)


ROOM_WALLS = (((1.525, 0.0), (0.05, 3.1, 0.25)), ((-1.525, 0.0), (0.05, 3.1, 0.25)),
              ((0.0, 1.525), (3.0, 0.05, 0.25)), ((0.0, -1.525), (3.0, 0.05, 0.25)))
"""room.urdf's wall boxes (centre, size): they cast shadows too."""
MAX_SHADOW = 1.5
"""m; a low light's shadows are cut at this length."""


def shadow_polygons(scene: Scene, clutter: list[Furniture], direction: list[float]
                    ) -> list[np.ndarray]:
    """Floor shadows of the fixed things (room walls, the task's boxes and walls, clutter)
    under a light from ``direction``: each footprint and its top projected along the light.
    Movable blocks cast none (they move; a 5 cm cube's shadow is a few pixels)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    if d[2] <= 0.02:
        return []
    push = -d[:2] / d[2]  # floor offset per metre of height
    boxes = [(xy, size, 0.0) for xy, size in ROOM_WALLS]
    for piece in scene.pieces:
        box = piece.as_box() if isinstance(piece, Wall) else piece
        if isinstance(box, Box):
            boxes.append((box.xy, box.size, box.yaw))
    for f in clutter:
        size = (2 * f.size[0], 2 * f.size[0], f.size[2]) if f.kind == "cylinder" else f.size
        boxes.append((f.xy, size, f.yaw))
    out = []
    for xy, size, yaw in boxes:
        base = _footprint(xy, size, yaw)
        offset = push * size[2]
        length = float(np.linalg.norm(offset))
        if length > MAX_SHADOW:
            offset *= MAX_SHADOW / length
        out.append(np.vstack([base, base + offset]))
    return out


def shadow_darkness(sim: SimConfig) -> float:
    """The light left in a shadow: the ambient term over ambient plus the direct light on
    the floor (TinyRenderer's coefficients)."""
    d = np.asarray(sim.light_direction, float)
    sin_elevation = max(float(d[2] / np.linalg.norm(d)), 0.0)
    return AMBIENT / (AMBIENT + DIFFUSE * sin_elevation)


def clutter_of(scene: Scene, sim: SimConfig) -> list[Furniture]:
    """The ``[sim] clutter`` pieces around ``scene`` (from ``[sim] look_seed``)."""
    return furniture(sim.clutter, sim.look_seed, scene)


def dress(client: int, room: int, scene: Scene, sim: SimConfig,
          clutter: list[Furniture]) -> list[int]:
    """Textures on the room (when ``textured(sim)``, with the shadows of fixed things baked
    into the floor) and the ``clutter`` pieces (``clutter_of``); the clutter's bodies."""
    if textured(sim):
        shadows = (shadow_polygons(scene, clutter, list(sim.light_direction))
                   if sim.shadows else [])
        dress_room(client, room, sim, shadows)
    return [build_furniture(client, piece) for piece in clutter]


def motion(client: int, robot: int) -> tuple[float, float]:
    """(yaw rate rad/s, horizontal speed m/s) of the robot now, for the camera's motion
    blur."""
    (vx, vy, _), (_, _, wz) = p.getBaseVelocity(robot, physicsClientId=client)
    return (wz, math.hypot(vx, vy))
