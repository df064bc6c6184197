"""The scene's look from ``[sim]``: floor, wall and block colours and the renderer's light.

Colours are set on the loaded bodies' visual shapes (``changeVisualShape``); the light goes
to every ``getCameraImage`` call. At the defaults the render is the same, pixel for pixel,
as with the URDFs' colours and PyBullet's default light (tests/test_sim_imperfections.py).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from jetbot_rt.sim.pybullet_import import import_pybullet

p = import_pybullet()

if TYPE_CHECKING:
    from jetbot_rt.sim.config import SimConfig

FLOOR_LIGHT = (0.69, 0.667, 0.627)
FLOOR_DARK = (0.439, 0.424, 0.4)
"""room.urdf's two greys of the checkerboard (visuals 0 and 1); a dark tile keeps this ratio
to ``floor_color`` in each channel (about 0.64)."""
WALL_COLORS = (
    (0.55, 0.70, 0.85),  # +x blue
    (0.60, 0.80, 0.60),  # -x green
    (0.85, 0.80, 0.55),  # +y sand
    (0.72, 0.66, 0.85),  # -y lavender
)
"""room.urdf's wall colours, its visuals 2..5."""
BLOCK_COLOR = (0.9, 0.05, 0.05)
"""block.urdf's red."""
AMBIENT, DIFFUSE, SPECULAR = 0.6, 0.35, 0.05
"""TinyRenderer's default light coefficients."""


def wall_colors(sim: SimConfig) -> list[tuple[float, ...]]:
    """The four walls' colours (+x, -x, +y, -y) from ``wall_color``: one colour for all, four
    in a row, or (none) the four heading colours."""
    if sim.wall_color is None:
        return [tuple(c) for c in WALL_COLORS]
    if len(sim.wall_color) == 3:
        return [tuple(sim.wall_color)] * 4
    return [tuple(sim.wall_color[i:i + 3]) for i in range(0, 12, 3)]


def apply_colors(client: int, room: int, block: int | None, sim: SimConfig) -> None:
    """Colour the floor tiles, the four walls and the goal block, if given (only those that
    differ from the URDFs' colours: a set colour passes through float32 and may shift a
    pixel)."""
    light = tuple(sim.floor_color)
    dark = light if sim.floor_texture == "plain" else tuple(
        c * dark / base for c, dark, base in zip(light, FLOOR_DARK, FLOOR_LIGHT, strict=True)
    )
    wanted = [light, dark, *wall_colors(sim)]
    urdf = [FLOOR_LIGHT, FLOOR_DARK, *WALL_COLORS]
    for shape, (rgb, default) in enumerate(zip(wanted, urdf, strict=True)):
        if tuple(rgb) != default:
            p.changeVisualShape(room, -1, shapeIndex=shape, rgbaColor=(*rgb, 1.0),
                                physicsClientId=client)
    if block is not None and tuple(sim.block_color) != BLOCK_COLOR:
        p.changeVisualShape(block, -1, rgbaColor=(*sim.block_color, 1.0),
                            physicsClientId=client)


def light_kwargs(sim: SimConfig) -> dict[str, Any]:
    """``getCameraImage`` keyword arguments for the light: its direction, strength and
    colour (``[sim] light_color``, passed only when not white)."""
    k = sim.light_intensity
    out: dict[str, Any] = {
        "lightDirection": list(sim.light_direction),
        "lightAmbientCoeff": AMBIENT * k,
        "lightDiffuseCoeff": DIFFUSE * k,
        "lightSpecularCoeff": SPECULAR * k,
        # TinyRenderer's shadow map darkens little (0.55 grey levels over a frame with a 40 cm
        # box in it) at 1.7x the render (benchmarks/bench_sim_choices.py): sim/looks.py bakes
        # the shadows into the floor instead
        "shadow": 0,
    }
    if [float(c) for c in sim.light_color] != [1.0, 1.0, 1.0]:
        out["lightColor"] = [float(c) for c in sim.light_color]
    return out
