"""The per-episode draw of the appearance families (``[randomize] appearance = true``), and the
held-out test that keeps evaluation looks out of training.

``sample_looks`` runs after every other draw of ``randomize.sample``, from the same seeded
generator, so with ``appearance`` off no seed draws anything different from before. It sets
the floor's family and colour, the walls' texture, colour and skirting, clutter, lamps, the
window, the light's colour and shadows, the camera's look and ``look_seed`` (which seeds
the textures' and clutter's details).

Held out (``held_out``): a floor whose family is not in ``[randomize] floor_families``
(carpet and rug by default), or whose colour lies in one of ``heldout_floor_hsv``'s boxes (a
mid oak brown and a dark blue-grey by default). A training draw never makes either: its
family comes from the list, its colour is drawn again while it falls in a box.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from jetbot_rt.errors import UsageError
from jetbot_rt.sim.textures import home_color, hsv_of, kelvin_rgb

if TYPE_CHECKING:
    from jetbot_rt.sim.config import RandomizeConfig, SimConfig

COLOR_ATTEMPTS = 64
SKIRTINGS = ((0.95, 0.95, 0.93), (0.45, 0.3, 0.18), (0.35, 0.35, 0.35))
"""White, wood, grey."""


def plain_float(value: float) -> float:
    """A plain float, rounded to 6 digits so that a report or a TOML file reads well."""
    return round(float(value), 6)


_r = plain_float


def in_boxes(color: list[float] | tuple[float, ...], boxes: list[float]) -> bool:
    """Whether an RGB colour's (hue degrees, saturation, value) lies in one of ``boxes`` (6
    numbers each: hue, saturation, value, each low then high)."""
    h, s, v = hsv_of((float(color[0]), float(color[1]), float(color[2])))
    for i in range(0, len(boxes), 6):
        h0, h1, s0, s1, v0, v1 = boxes[i:i + 6]
        if h0 <= h <= h1 and s0 <= s <= s1 and v0 <= v <= v1:
            return True
    return False


def held_out(sim: SimConfig, ranges: RandomizeConfig) -> str | None:
    """Why ``sim``'s look is one a training draw of ``ranges`` never makes, or None."""
    if sim.floor_texture not in ranges.floor_families:
        return f"floor family {sim.floor_texture!r} is not in [randomize] floor_families"
    if in_boxes(sim.floor_color, ranges.heldout_floor_hsv):
        return f"floor colour {sim.floor_color} lies in [randomize] heldout_floor_hsv"
    return None


def floor_color(rng: np.random.Generator, r: RandomizeConfig) -> list[float]:
    """A floor colour at any hue (never one that could pass for the red goal), drawn again
    while it lies in a held-out box."""
    for _ in range(COLOR_ATTEMPTS):
        color = [_r(c) for c in home_color(rng, None, tuple(r.floor_saturation),
                                           tuple(r.floor_value))]
        if not in_boxes(color, r.heldout_floor_hsv):
            return color
    raise UsageError("[randomize] heldout_floor_hsv covers the floor colours that "
                     "floor_saturation and floor_value draw: widen them or narrow the boxes")


def sample_looks(base: SimConfig, r: RandomizeConfig, rng: np.random.Generator
                 ) -> dict[str, Any]:
    """One episode's appearance: ``[sim]`` keys and values (always the same number of draws
    in the same order, whatever comes out, except the floor colour's redraws)."""
    family = r.floor_families[int(rng.integers(len(r.floor_families)))]
    floor = floor_color(rng, r)
    home_walls = rng.random() < r.home_walls
    wall = [_r(c) for c in home_color(rng, None, (0.0, 0.3), (0.55, 0.95))]
    wall_texture = r.wall_textures[int(rng.integers(len(r.wall_textures)))]
    skirting = rng.random() < r.skirting
    skirting_color = [_r(c) for c in SKIRTINGS[int(rng.integers(len(SKIRTINGS)))]]
    clutter = int(rng.integers(int(r.clutter[0]), int(r.clutter[1]) + 1))
    lamps = int(rng.integers(int(r.lamps[0]), int(r.lamps[1]) + 1))
    window = rng.uniform(*r.window_light)
    kelvin = rng.uniform(*r.light_temperature)
    shadows = bool(rng.random() < r.shadows)
    low, high = r.exposure
    exposure = math.exp(rng.uniform(math.log(low), math.log(high)))
    balance = rng.uniform(*r.white_balance, 2)
    drawn: dict[str, Any] = {
        "floor_texture": family,
        "floor_color": floor,
        "wall_texture": wall_texture,
        "skirting_color": skirting_color if skirting else None,
        "clutter": clutter,
        "lamps": lamps,
        "window_light": _r(window),
        "light_color": [_r(c) for c in kelvin_rgb(kelvin)],
        "shadows": shadows,
        "exposure": _r(exposure),
        "white_balance": [_r(balance[0]), 1.0, _r(balance[1])],
        "gain_noise": _r(rng.uniform(*r.gain_noise)),
        "vignetting": _r(rng.uniform(*r.vignetting)),
        "motion_blur": _r(rng.uniform(*r.motion_blur)),
        "look_seed": int(rng.integers(2**31 - 1)),
    }
    if home_walls:
        drawn["wall_color"] = wall
    del base  # the families replace [sim]'s looks; nothing of it is scaled
    return drawn


LOOK_KEYS = ("floor_texture", "floor_color", "wall_texture", "wall_color", "skirting_color",
             "clutter", "lamps", "window_light", "light_color", "shadows", "exposure",
             "white_balance", "gain_noise", "vignetting", "motion_blur", "look_seed")
"""The [sim] keys ``sample_looks`` may set."""
