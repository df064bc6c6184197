"""Procedural floor and wall textures as homes have them, drawn from a seed with numpy/OpenCV.

Each generator takes the family's base colour (RGB in 0..1) and a ``numpy.random.Generator``
and returns a uint8 RGB image; the same generator state gives the same image bit for bit
(only numpy draws and deterministic OpenCV filters are used). The texture's mean colour stays
near the base colour, so ``[sim] floor_color`` sets the floor's hue and lightness whatever
the family; the family adds its structure (planks and grain, grout lines, pile, a rug's
pattern, concrete's mottling and joints).

The floor texture covers the whole 3 m x 3 m floor (``FLOOR_TEXELS`` texels a side, 1.2 cm
each: about what a 56x56 frame resolves 0.3 m ahead; a grout line or a seam is one texel).
Light pools of lamps and a window's daylight are baked into it by ``bake_light``, the
shadows of fixed things by ``bake_shadows`` (TinyRenderer has one directional light, and
its shadow map darkens almost nothing; the rest is painted on).
"""

from __future__ import annotations

import colorsys
import math
from collections.abc import Callable

import cv2
import numpy as np

from jetbot_rt.sim.config import WALL_TEXTURES

FLOOR_TEXELS = 256
"""Texels a side of the floor texture (the floor is 3 m square): 1.2 cm texels, 4 times
cheaper to draw per episode than 512 (docs/SIM.md, "Appearance families")."""
FLOOR_SIZE_M = 3.0
LIGHT_TEXELS = 64
"""Texels a side of the light map baked into the floor (lamp pools and window light vary
over tens of centimetres: 4.7 cm texels, upsampled)."""
WALL_TEXELS = (256, 32)
"""(width, height) of a wall texture: 3 m long, 0.25 m high."""
WALL_HEIGHT_M = 0.25
CHECKER_DARK = 0.636
"""room.urdf's dark tiles over its light ones (the checker family keeps the ratio)."""

Rgb = tuple[float, float, float]


def _m(metres: float) -> float:
    """Texels of the floor texture per ``metres``."""
    return metres * FLOOR_TEXELS / FLOOR_SIZE_M


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[int, int]
                 ) -> np.ndarray:
    """Value noise in [-1, 1]: a ``cells`` grid of uniform draws, cubic-upsampled to ``shape``
    (rows, columns)."""
    low = rng.uniform(-1.0, 1.0, (cells[0] + 1, cells[1] + 1)).astype(np.float32)
    return cv2.resize(low, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)


def fractal_noise(rng: np.random.Generator, shape: tuple[int, int], base_cells: int,
                  octaves: int) -> np.ndarray:
    """Octaves of ``smooth_noise`` (each twice as fine, half as strong), about [-1, 1]."""
    out = np.zeros(shape, np.float32)
    weight, total = 1.0, 0.0
    for octave in range(octaves):
        cells = base_cells * 2**octave
        out += weight * smooth_noise(rng, shape, (cells, cells))
        total += weight
        weight *= 0.5
    return out / total


def _shade(base: Rgb, factor: np.ndarray) -> np.ndarray:
    """HxWx3 float32: ``base`` times a per-texel brightness factor (HxW or HxWx3)."""
    f = factor if factor.ndim == 3 else factor[:, :, None]
    return f * np.asarray(base, np.float32)[None, None, :]


def _to_u8(image: np.ndarray) -> np.ndarray:
    return np.clip(image * np.float32(255.0) + np.float32(0.5), 0, 255).astype(np.uint8)


def checker(base: Rgb, rng: np.random.Generator) -> np.ndarray:
    """room.urdf's 0.25 m checkerboard: light tiles ``base``, dark ones 0.636 of it."""
    del rng  # nothing random: the checker of the untextured room, as a texture
    idx = np.arange(FLOOR_TEXELS) * 12 // FLOOR_TEXELS
    dark = (idx[:, None] + idx[None, :]) % 2 == 1
    factor = np.where(dark, CHECKER_DARK, 1.0).astype(np.float32)
    return _to_u8(_shade(base, factor))


def plain(base: Rgb, rng: np.random.Generator) -> np.ndarray:
    """One colour (vinyl, paint): a faint large-scale unevenness of +-2 %."""
    factor = 1.0 + 0.02 * smooth_noise(rng, (FLOOR_TEXELS, FLOOR_TEXELS), (3, 3))
    return _to_u8(_shade(base, factor))


def wood(base: Rgb, rng: np.random.Generator) -> np.ndarray:
    """Planks 8-20 cm wide, 0.6-1.5 m long in staggered rows along x or y, each its own shade
    (+-12 %), with a grain of noise-bent stripes along the plank and dark 1-texel seams."""
    n = FLOOR_TEXELS
    width = round(_m(rng.uniform(0.08, 0.2)))
    length = round(_m(rng.uniform(0.6, 1.5)))
    along_x = rng.random() < 0.5
    grain_period = _m(rng.uniform(0.03, 0.07))  # between the grain's stripes
    grain_strength = rng.uniform(0.05, 0.14)
    rows = (n + width - 1) // width
    offsets = rng.uniform(0, length, rows)
    shades = rng.uniform(0.88, 1.12, (rows, n // max(length, 1) + 3))
    v, u = np.mgrid[0:n, 0:n].astype(np.float32)  # v: across planks, u: along them
    row = (v // width).astype(int)
    shifted = u + offsets[row]
    plank = (shifted // length).astype(int)
    factor = shades[row, plank].astype(np.float32)
    bend = _m(0.04) * fractal_noise(rng, (n, n), 6, 3)
    stripes = np.sin((v + bend + 0.15 * (shifted % length)) * (2 * math.pi / grain_period))
    factor *= 1.0 + grain_strength * stripes * (0.6 + 0.4 * fractal_noise(rng, (n, n), 16, 2))
    seam = ((v % width) < 1) | ((shifted % length) < 1)
    factor[seam] *= 0.7
    if not along_x:
        factor = factor.T
    return _to_u8(_shade(base, factor))


def carpet(base: Rgb, rng: np.random.Generator) -> np.ndarray:
    """Pile: texel-fine light and shade of the tufts (about +-8 %), a faint colour noise of
    the fibres (+-2 % per channel), soft blotches (+-6 %) where the pile lies differently,
    and no straight line anywhere."""
    n = FLOOR_TEXELS
    pile = rng.random((n, n), dtype=np.float32) - np.float32(0.5)  # light and shade of tufts
    pile = cv2.GaussianBlur(pile, (0, 0), 0.7) * np.float32(0.4) + pile * np.float32(0.06)
    fibre = (rng.random((n, n, 3), dtype=np.float32) - np.float32(0.5)) * np.float32(0.04)
    blotch = 0.06 * fractal_noise(rng, (n, n), 8, 3)
    return _to_u8(_shade(base, 1.0 + (pile + blotch)[:, :, None] + fibre))


def tiles(base: Rgb, rng: np.random.Generator) -> np.ndarray:
    """Square tiles of 0.2-0.6 m, each its own shade (+-6 %) with a faint marbling, between
    grout lines 3-8 mm wide, light or dark."""
    n = FLOOR_TEXELS
    size = _m(rng.uniform(0.2, 0.6))
    grout_w = max(1.0, _m(rng.uniform(0.003, 0.008)))
    grout = (0.85, 0.84, 0.8) if rng.random() < 0.6 else (0.25, 0.24, 0.23)
    x0, y0 = rng.uniform(0, size, 2)
    v, u = np.mgrid[0:n, 0:n].astype(np.float32)
    cu, cv_ = ((u + x0) // size).astype(int), ((v + y0) // size).astype(int)
    shades = rng.uniform(0.94, 1.06, (cv_.max() + 1, cu.max() + 1)).astype(np.float32)
    factor = shades[cv_, cu] * (1.0 + 0.05 * fractal_noise(rng, (n, n), 12, 3))
    image = _shade(base, factor)
    line = (((u + x0) % size) < grout_w) | (((v + y0) % size) < grout_w)
    image[line] = np.asarray(grout, np.float32) * np.float32(rng.uniform(0.9, 1.1))
    return _to_u8(image)


def concrete(base: Rgb, rng: np.random.Generator) -> np.ndarray:
    """Polished concrete: mottling of several scales (+-10 %), speckles of aggregate, and saw
    cut joints every 1-1.5 m."""
    n = FLOOR_TEXELS
    factor = 1.0 + 0.1 * fractal_noise(rng, (n, n), 4, 5)
    speck = rng.random((n, n)) < 0.01
    factor[speck] *= rng.uniform(0.75, 1.2, int(speck.sum())).astype(np.float32)
    joint = _m(rng.uniform(1.0, 1.5))
    x0, y0 = rng.uniform(0, joint, 2)
    v, u = np.mgrid[0:n, 0:n].astype(np.float32)
    cut = (((u + x0) % joint) < 1) | (((v + y0) % joint) < 1)
    factor[cut] *= 0.7
    return _to_u8(_shade(base, factor))


def rug(base: Rgb, rng: np.random.Generator) -> np.ndarray:
    """A patterned rug on a floor: the floor around it is wood or plain in ``base``; the rug
    (1.2-2.4 m by 0.9-2 m, somewhere on the floor) has a field in a second colour, a border of
    bands in a third, and a pattern of diamonds, stripes or medallions, all with carpet pile.
    The rug's colours are drawn near ``base``'s lightness, at any hue but never a saturated
    red (``avoid_goal_hue``: the goal is a red block)."""
    n = FLOOR_TEXELS
    floor = wood(base, rng) if rng.random() < 0.5 else plain(base, rng)
    field_rgb = home_color(rng, hue=None, saturation=(0.2, 0.7), value=(0.25, 0.8))
    border_rgb = home_color(rng, hue=None, saturation=(0.1, 0.7), value=(0.15, 0.9))
    motif_rgb = home_color(rng, hue=None, saturation=(0.0, 0.6), value=(0.3, 0.95))
    w, h = int(_m(rng.uniform(1.4, 2.6))), int(_m(rng.uniform(1.0, 2.2)))
    if rng.random() < 0.5:
        w, h = h, w
    # about the room's middle, where the robot drives
    x0 = int(np.clip((n - w) / 2 + _m(rng.uniform(-0.4, 0.4)), 0, n - w))
    y0 = int(np.clip((n - h) / 2 + _m(rng.uniform(-0.4, 0.4)), 0, n - h))
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    edge = np.minimum(np.minimum(u, w - 1 - u), np.minimum(v, h - 1 - v))
    band = _m(rng.uniform(0.06, 0.15))
    kind = int(rng.integers(3))
    period = _m(rng.uniform(0.12, 0.35))
    if kind == 0:  # diamonds
        motif = ((np.abs((u % period) - period / 2) + np.abs((v % period) - period / 2))
                 < period * 0.3)
    elif kind == 1:  # stripes
        motif = (u % period) < period * 0.4
    else:  # medallions
        motif = np.hypot((u % period) - period / 2, (v % period) - period / 2) < period * 0.3
    image = np.empty((h, w, 3), np.float32)
    image[:] = field_rgb
    image[motif] = motif_rgb
    image[edge < band] = border_rgb
    image[(edge >= band * 0.4) & (edge < band * 0.6)] = motif_rgb
    pile = 1.0 + 0.15 * (rng.random((h, w, 1), dtype=np.float32) - np.float32(0.5))
    out = floor.copy()
    out[y0:y0 + h, x0:x0 + w] = _to_u8(image * pile)
    return out


FLOORS: dict[str, Callable[[Rgb, np.random.Generator], np.ndarray]] = {
    "checker": checker, "plain": plain, "wood": wood, "carpet": carpet, "tiles": tiles,
    "rug": rug, "concrete": concrete,
}
"""The floor families, by ``[sim] floor_texture`` name."""


def hsv_of(color: Rgb) -> tuple[float, float, float]:
    """(hue in degrees, saturation, value) of an RGB colour in 0..1."""
    h, s, v = colorsys.rgb_to_hsv(*color)
    return (h * 360.0, s, v)


def hue_distance(a: float, b: float) -> float:
    """Degrees between two hues, 0..180."""
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


GOAL_HUE = 0.0
"""The goal block's hue (red); colours near it are kept unsaturated (``goal_like``)."""
GOAL_HUE_MARGIN = 35.0
GOAL_SATURATION_LIMIT = 0.35


def goal_like(color: Rgb, goal_hue: float = GOAL_HUE) -> bool:
    """Whether ``color`` could pass for the goal block: within 35 degrees of its hue and
    saturated above 0.35 (and not too dark to show a hue)."""
    h, s, v = hsv_of(color)
    return hue_distance(h, goal_hue) < GOAL_HUE_MARGIN and s > GOAL_SATURATION_LIMIT and v > 0.2


def home_color(rng: np.random.Generator, hue: tuple[float, float] | None,
               saturation: tuple[float, float], value: tuple[float, float],
               goal_hue: float = GOAL_HUE) -> Rgb:
    """A colour drawn in HSV (hue in degrees, ``None``: any), never ``goal_like``: a colour near
    the goal's hue gets its saturation capped instead of being drawn again (one draw per call
    whatever comes out, so the generator's state after it is fixed)."""
    h = rng.uniform(*(hue or (0.0, 360.0))) % 360.0
    s = rng.uniform(*saturation)
    v = rng.uniform(*value)
    if hue_distance(h, goal_hue) < GOAL_HUE_MARGIN:
        s = min(s, GOAL_SATURATION_LIMIT * 0.9)
    r, g, b = colorsys.hsv_to_rgb(h / 360.0, s, v)
    return (r, g, b)


def floor_texture(family: str, base: Rgb, seed: int) -> np.ndarray:
    """The floor's texture, ``FLOOR_TEXELS`` square, row 0 at y = -1.5 m, column 0 at
    x = -1.5 m: family ``family`` in colour ``base``, details from ``seed``."""
    return FLOORS[family](base, np.random.default_rng([seed, 1]))


def bake_light(texture: np.ndarray, lamps: int, window: float, seed: int) -> np.ndarray:
    """``texture`` under ``lamps`` warm light pools (radius 0.4-0.9 m, +25-60 % at their
    centre, 2400-3500 K) and, with ``window`` > 0, a window's daylight: a bright, slightly
    blue slanted patch (+``window`` x 60 %) from one wall. The renderer's own light and
    shadows come on top (TinyRenderer has one light; these are painted on)."""
    if lamps == 0 and window <= 0:
        return texture
    rng = np.random.default_rng([seed, 2])
    n = LIGHT_TEXELS  # light varies slowly: computed coarse, then upsampled
    scale = n / texture.shape[0]
    v, u = np.mgrid[0:n, 0:n].astype(np.float32)
    light = np.ones((n, n, 3), np.float32)
    for _ in range(lamps):
        cx, cy = rng.uniform(0.1 * n, 0.9 * n, 2)
        radius = _m(rng.uniform(0.4, 0.9)) * scale
        gain = rng.uniform(0.25, 0.6)
        warm = np.asarray(kelvin_rgb(rng.uniform(2400, 3500)), np.float32)
        pool = np.exp(-((u - cx) ** 2 + (v - cy) ** 2) / (2 * (radius / 2) ** 2))
        light += gain * pool[:, :, None] * warm[None, None, :]
    if window > 0:
        side = int(rng.integers(4))
        start, width = rng.uniform(0.1, 0.6) * n, rng.uniform(0.2, 0.35) * n
        depth, slant = rng.uniform(0.3, 0.6) * n, rng.uniform(-0.6, 0.6)
        along, into = (u, v) if side in (0, 1) else (v, u)
        if side in (1, 3):
            into = n - 1 - into
        lo = start + slant * into
        patch = ((along > lo) & (along < lo + width) & (into < depth)).astype(np.float32)
        patch = cv2.GaussianBlur(patch, (0, 0), 1.0) * np.clip(1.0 - into / depth, 0.3, 1.0)
        sky = np.asarray(kelvin_rgb(6500.0), np.float32) * np.float32(0.6 * window)
        light += patch[:, :, None] * sky[None, None, :]
    size = texture.shape[1], texture.shape[0]
    light = cv2.resize(light, size, interpolation=cv2.INTER_LINEAR)
    return np.clip(texture * light + np.float32(0.5), 0, 255).astype(np.uint8)


WALL_STYLES = WALL_TEXTURES
"""``[sim] wall_texture``'s choices (the schema's own tuple, not a copy to keep in step)."""
SKIRTING_M = 0.06
"""Height of a skirting board."""


def wall_texture(style: str, base: Rgb, skirting: Rgb | None, seed: int) -> np.ndarray:
    """One wall's texture (``WALL_TEXELS``; row 0 at the top of the wall): ``style`` in
    ``base`` (flat; paint: a roller's faint mottling; wallpaper: stripes or a small repeat in
    a second shade; panel: vertical boards with dark joints), and a ``skirting`` board
    ``SKIRTING_M`` high at the bottom with a shadow line above it (None: none)."""
    rng = np.random.default_rng([seed, 3])
    w, h = WALL_TEXELS
    factor = np.ones((h, w), np.float32)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    if style == "paint":
        factor += 0.03 * fractal_noise(rng, (h, w), 8, 3)
    elif style == "wallpaper":
        period = rng.uniform(6, 24)
        contrast = rng.uniform(0.06, 0.18)
        if rng.random() < 0.5:
            factor -= contrast * ((u % period) < period / 2)
        else:
            factor -= contrast * ((np.abs((u % period) - period / 2)
                                   + np.abs((v % period) - period / 2)) < period / 4)
    elif style == "panel":
        period = rng.uniform(12, 30)
        factor *= 1.0 + 0.05 * smooth_noise(rng, (h, w), (1, int(w / period) + 1))
        factor[(u % period) < 1] *= 0.6
    image = _shade(base, factor)
    if skirting is not None:
        board = round(h * SKIRTING_M / WALL_HEIGHT_M)
        image[h - board:] = np.asarray(skirting, np.float32)
        image[h - board - 1] *= 0.55
    return _to_u8(image)


def kelvin_rgb(kelvin: float) -> Rgb:
    """The colour of a black body at ``kelvin`` (1000-12000 K), normalised so its largest
    channel is 1 (Tanner Helland's fit of the CIE 1964 curve, the usual approximation)."""
    t = min(max(kelvin, 1000.0), 12000.0) / 100.0
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = (99.4708025861 * math.log(t) - 161.1195681661 if t <= 66
         else 288.1221695283 * (t - 60) ** -0.0755148492)
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * math.log(t - 10)
                               - 305.0447927307)
    rgb = [min(max(c, 0.0), 255.0) for c in (r, g, b)]
    top = max(rgb)
    return (rgb[0] / top, rgb[1] / top, rgb[2] / top)


def bake_shadows(texture: np.ndarray, polygons: list[np.ndarray], darkness: float
                 ) -> np.ndarray:
    """``texture`` (the floor's, row 0 at y = -1.5 m) darkened to ``darkness`` (0..1, the
    share of light left in a shadow) inside ``polygons`` (each an Nx2 array of floor points,
    m), with edges softened over about 2 cm (a penumbra)."""
    if not polygons or darkness >= 1.0:
        return texture
    n = texture.shape[0]
    mask = np.zeros(texture.shape[:2], np.float32)
    for polygon in polygons:
        texels = np.rint((np.asarray(polygon) + FLOOR_SIZE_M / 2) * (n / FLOOR_SIZE_M))
        hull = cv2.convexHull(texels.astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1.0)
    mask = cv2.GaussianBlur(mask, (0, 0), max(_m(0.015), 0.5))
    light = 1.0 - (1.0 - np.float32(darkness)) * mask
    return np.clip(texture * light[:, :, None] + np.float32(0.5), 0, 255).astype(np.uint8)
