"""The ``[sim]`` and ``[randomize]`` sections, beside the world they configure.

Each randomized ``[sim]`` knob declares its own ``[randomize]`` range in its metadata
(``randomized``): ``RandomizeConfig``'s keys are made from those declarations, and
``sim/randomize.py`` draws every knob declared ``"value"`` or ``"factor"`` without naming it, so
a new randomized knob is one field here (and the code that uses it). The fault injection keys
(``SimFaults``) are test-only and declared apart from the user's knobs (``SimKnobs``); both are
read from ``[sim]``.

``Config`` (``config/sections.py``) imports this module on the robot's Python 3.8: it imports
nothing of the simulator (no pybullet, no numpy), its annotations are ``Optional``/``List``, and
pyproject.toml and tests/test_packaging.py list it as the one robot-side file in ``sim/``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, List, Optional

from jetbot_rt.config.schema import check, low_high, meta, one_of, pair, rgb, within

FLOOR_TEXTURES = ("checker", "plain", "wood", "carpet", "tiles", "rug", "concrete")
WALL_TEXTURES = ("flat", "paint", "wallpaper", "panel")
LENSES = ("pinhole", "fisheye")

DRAWS = ("value", "factor", "offset", "color", "custom")
"""How a draw sets a knob: the range's value itself, the ``[sim]`` value times a factor from
the range, the ``[sim]`` value plus a number from the range (a range around a measured value
that may be 0), a colour (one factor on all channels, then ``tint`` on each), or by code of its
own in ``randomize.sample`` (more than one number drawn, or a range in other units)."""


@dataclass(frozen=True)
class Randomized:
    """A knob's ``[randomize]`` range: its default, the bounds a user's range must keep, and
    how a draw applies it (``DRAWS``)."""

    default: tuple[float, float]
    low: float
    high: float
    draw: str
    unit: str = ""
    key: Optional[str] = None
    """The ``[randomize]`` key when it is not the knob's name (a range in other units)."""
    optional: bool = False
    """The range may be set to none (the knob then keeps its ``[sim]`` value)."""
    doc: str = ""
    late: bool = False
    """Drawn after every other knob (a knob added after the first draws were published, so
    that every earlier draw of a seed stays as it was)."""


def randomized(default: tuple[float, float], low: float, high: float, draw: str,
               unit: str = "", *, key: str | None = None, optional: bool = False,
               doc: str = "", late: bool = False) -> dict[str, Any]:
    """Field metadata: this knob is drawn per episode from a ``[randomize]`` range (by
    default ``default``) that must lie in [``low``, ``high``]."""
    assert draw in DRAWS, draw
    return {"randomize": Randomized(default, low, high, draw, unit, key, optional, doc, late)}


@dataclass
class SimKnobs:
    """The ``[sim]`` keys a user sets: the world, its motors and its camera."""

    physics_hz: float = field(default=120.0, metadata=within(10.0, 10000.0, " Hz"))
    """Physics sub-step rate; each control tick advances the world by one period (4 sub-steps
    at 30 Hz: the cheapest that keeps 240 Hz's trajectories, docs/SIM.md)."""
    motor_gain: float = field(default=20.0, metadata=meta(
        within(0.01, 1000.0),
        randomized((0.9, 1.1), 0.1, 3, "factor",
                   doc="Factor on both wheels' speed (battery voltage, wheel size)."),
    ))
    """Wheel angular velocity (rad/s) at duty 1.0."""
    motor_tau: float = field(default=0.05, metadata=within(0.0, 10.0, " s"))
    """First-order lag time constant of the motor (s); 0 for none."""
    supersample: int = field(default=1, metadata=within(1, 4))
    """Render the camera image this many times wider and taller and area-average it down to
    the policy's size: closer to what the real camera's scaled frame shows, at about this
    factor squared times the render cost (docs/SIM.md, "The render-size seam")."""
    seed: int = 0
    """Seeds the scene (where the task puts its blocks, as the env's ``reset(seed=...)``),
    the camera's image noise (``image_noise``) and the one draw of ``[randomize]``."""
    task: Optional[str] = None
    """The scene to build: a task's name (``forward``, ``seek``, ``FILE.py:Class``,
    ``module:Class``, an installed plugin's; docs/TASKS.md). Default: the policy's
    ``jetbot_rt.task`` metadata (a built-in or plugin name only), else ``forward``."""
    wheel_gain: List[float] = field(default_factory=lambda: [1.0, 1.0], metadata=meta(
        pair(0, 2, open_low=True),
        randomized((0.8, 1.2), 0.1, 2, "custom", doc="Factor, drawn for each wheel apart."),
    ))
    """[left, right]: multiplies each wheel motor's speed and torque (a loose wheel, a worn
    gearbox). The robot's own [actions] trim is the runtime's answer to it."""
    deadband: float = field(default=0.0, metadata=meta(
        within(0, 1, open_high=True),
        randomized((0.0, 0.3), 0, 0.99, "value",
                   doc="A task trains only with a max_speed above the top of this range."),
    ))
    """Duty below which a wheel does not turn (gearbox friction); above it the speed is
    motor_gain * (|duty| - deadband)."""
    latency: float = field(default=0.0, metadata=meta(
        within(0, 1, " s"), randomized((0.0, 0.2), 0, 1, "value", " s"),
    ))
    """Seconds from a duty write to the motor acting on it (whole physics sub-steps)."""
    camera_latency: float = field(default=0.0, metadata=meta(
        within(0, 1, " s"), randomized((0.0, 0.12), 0, 1, "value", " s"),
    ))
    """Seconds from the world's state to the frame that shows it (whole physics sub-steps)."""
    stall_torque: Optional[float] = field(default=None, metadata=meta(
        within(1e-6, 1e6),
        randomized((0.05, 0.1), 0.001, 10, "custom", " N m", optional=True,
                   doc="N m; none keeps [sim] stall_torque."),
    ))
    """N m per wheel at duty 1 and standstill: torque then scales with duty and falls with
    speed, as a PWM-driven DC motor's. Default: the ideal motor, 0.15 N m at any duty."""
    camera_pitch_deg: float = field(default=20.0, metadata=meta(
        within(-60, 80, " degrees"),
        randomized((0.8, 1.2), 0, 3, "factor", doc="Factor (duckietown: camera angle 0.8..1.2)."),
    ))
    """Camera tilt below the horizon."""
    camera_height: float = field(default=0.115, metadata=meta(
        within(0.04, 0.5, " m"),
        randomized((0.92, 1.08), 0.35, 4.3, "factor", doc="Factor (duckietown: 0.92..1.08)."),
    ))
    """Height of the camera's optical centre above the floor."""
    camera_vfov_deg: float = field(default=52.0, metadata=meta(
        within(10, 150, " degrees"),
        randomized((0.8, 1.2), 0.2, 2.8, "factor",
                   doc="Factor (duckietown: camera_fov_y 0.8..1.2)."),
    ))
    """Vertical field of view of the (pinhole) camera image."""
    floor_color: List[float] = field(default_factory=lambda: [0.69, 0.667, 0.627], metadata=meta(
        rgb(),
        randomized((0.35, 1.4), 0, 5, "color",
                   doc="Factor on all three channels (lighter or darker), then ``tint``."),
    ))
    """The floor's light tiles; dark tiles are this times 0.636."""
    floor_texture: str = field(default="checker", metadata=one_of(FLOOR_TEXTURES))
    """"checker" (0.25 m tiles) or "plain" (every tile floor_color); or a procedural texture
    in floor_color from ``look_seed``: "wood", "carpet", "tiles", "rug", "concrete"."""
    wall_color: Optional[List[float]] = field(default=None, metadata=meta(
        check(
            lambda v: len(v) in (3, 12) and all(0 <= x <= 1 for x in v),
            "[r, g, b] or four of them in a row (12 numbers), in 0..1",
        ),
        randomized((0.7, 1.3), 0, 5, "custom",
                   doc="Factor on all three channels of each wall apart, then ``tint``."),
    ))
    """[r, g, b]: all four walls this colour; 12 numbers: the walls at +x, -x, +y, -y in
    turn. Default: one colour each (blue +x, green -x, sand +y, lavender -y)."""
    block_color: List[float] = field(default_factory=lambda: [0.9, 0.05, 0.05], metadata=meta(
        rgb(), randomized((0.8, 1.1), 0, 5, "color", doc="Factor on all three channels, then "
                                                          "``tint``."),
    ))
    """The goal block."""
    light_direction: List[float] = field(
        default_factory=lambda: [-50.0, 30.0, 100.0],
        metadata=meta(
            check(
                lambda v: len(v) == 3 and all(math.isfinite(x) for x in v) and any(v),
                "three numbers, not all zero",
            ),
            randomized((30.0, 90.0), -90, 90, "custom", key="light_elevation_deg",
                       doc="light_direction: this elevation above the floor, from any azimuth."),
        ),
    )
    """World-frame direction towards the light (PyBullet's default)."""
    light_intensity: float = field(default=1.0, metadata=meta(
        within(0, 3), randomized((0.5, 1.3), 0, 3, "value"),
    ))
    """Scales the renderer's ambient (0.6), diffuse (0.35) and specular (0.05) light."""
    image_noise: float = field(default=0.0, metadata=meta(
        within(0, 1), randomized((0.0, 0.03), 0, 1, "value"),
    ))
    """Standard deviation of Gaussian pixel noise, as a fraction of full scale (255)."""
    image_blur: float = field(default=0.0, metadata=meta(
        within(0, 0.1), randomized((0.0, 0.006), 0, 0.1, "value"),
    ))
    """Gaussian blur sigma as a fraction of the image width (0.005: 1.1 px at 224)."""
    image_brightness: float = field(default=0.0, metadata=meta(
        within(-1, 1), randomized((-0.1, 0.1), -1, 1, "value"),
    ))
    """Added to every pixel, as a fraction of full scale."""
    image_contrast: float = field(default=1.0, metadata=meta(
        within(0, 3), randomized((0.8, 1.2), 0, 3, "value"),
    ))
    """Scales each pixel's distance from mid-grey."""
    lens: str = field(default="fisheye", metadata=one_of(LENSES))
    """The camera's projection: "fisheye" (the JetBot's IMX219 lens, default): the OpenCV
    fisheye model (``lens_focal``, ``lens_center``, ``lens_k1``..``lens_k4``), rendered by
    warping a wider pinhole render (docs/SIM.md, "The lens"); or "pinhole"
    (``camera_vfov_deg``), the simulator's view before the lens was modelled."""
    lens_focal: float = field(default=1.0194, metadata=meta(
        within(0.2, 5.0),
        randomized((0.93, 1.07), 0.5, 2, "factor", late=True,
                   doc="Factor (the fisheye's field of view; camera_vfov_deg's for the pinhole)."),
    ))
    """Fisheye: the focal length over the frame's height (fy / height; square sensor pixels,
    so fx / width is this times 9/16). 1.0194: 734 px at 1280x720, the IMX219's 160-degree
    lens taken as equidistant (docs/SIM.md, "The camera")."""
    lens_center: List[float] = field(default_factory=lambda: [0.5, 0.5],
                                     metadata=pair(0.3, 0.7))
    """Fisheye: the principal point (cx / width, cy / height)."""
    lens_k1: float = field(default=0.0, metadata=meta(
        within(-1, 1), randomized((-0.03, 0.03), -0.5, 0.5, "offset", late=True,
                                  doc="Added to [sim] lens_k1."),
    ))
    """Fisheye distortion: the angle in the image is theta (1 + k1 theta^2 + k2 theta^4 +
    k3 theta^6 + k4 theta^8) for a ray theta from the axis (OpenCV's cv2.fisheye model; all
    0: equidistant)."""
    lens_k2: float = field(default=0.0, metadata=meta(
        within(-1, 1), randomized((-0.01, 0.01), -0.5, 0.5, "offset", late=True,
                                  doc="Added to [sim] lens_k2."),
    ))
    lens_k3: float = field(default=0.0, metadata=within(-1, 1))
    lens_k4: float = field(default=0.0, metadata=within(-1, 1))


@dataclass
class SimFaults:
    """Fault injection, for tests and drills only: the sim's camera fails on purpose. Read
    from ``[sim]`` like the knobs, declared apart so that no user's key is mistaken for one."""

    camera_stall_after: Optional[float] = field(default=None, metadata=within(0.001, 1e6, " s"))
    """The camera delivers no new frame after this many simulated seconds."""
    blackout: Optional[List[float]] = field(
        default=None,
        metadata=check(lambda v: len(v) == 2 and 0 <= v[0] < v[1], "[start, end] seconds"),
    )
    """Frames are black between these simulated times (a covered lens)."""


@dataclass
class LookKnobs:
    """The room's appearance families and the camera's own look (``sim/looks.py``,
    ``sim/textures.py``, ``sim/clutter.py``, ``sim/camera_look.py``; docs/SIM.md, "Appearance
    families"). All off by default: the room and the frames are as without them."""

    wall_texture: str = field(default="flat", metadata=one_of(WALL_TEXTURES))
    """"flat" (one colour), "paint" (a roller's mottling), "wallpaper" (stripes or a small
    repeat) or "panel" (vertical boards), in each wall's ``wall_color``."""
    skirting_color: Optional[List[float]] = field(default=None, metadata=rgb())
    """[r, g, b]: a 6 cm skirting board at the bottom of every wall; default none."""
    clutter: int = field(default=0, metadata=within(0, 12))
    """Furniture-like boxes and cylinders along the walls, clear of the task's pieces."""
    lamps: int = field(default=0, metadata=within(0, 4))
    """Warm light pools (2400-3500 K) painted on the floor."""
    window_light: float = field(default=0.0, metadata=within(0, 2))
    """A window's daylight patch on the floor: its strength (1: 60 % brighter)."""
    light_color: List[float] = field(default_factory=lambda: [1.0, 1.0, 1.0],
                                     metadata=rgb())
    """The renderer light's colour (a warm lamp, cool daylight)."""
    shadows: bool = False
    """The fixed things (room walls, task boxes and walls, clutter) cast shadows along
    ``light_direction``, baked into the floor's texture when the room is built (no render
    time per frame; the movable blocks and the robot cast none)."""
    look_seed: int = field(default=0, metadata=within(0, 2**31 - 1))
    """Seeds the textures' details (planks, tiles, a rug's pattern), the lamps and window,
    and the clutter's pieces and places."""
    exposure: float = field(default=1.0, metadata=within(0.05, 8))
    """The camera's gain on linear light (0.5: a stop darker)."""
    white_balance: List[float] = field(default_factory=lambda: [1.0, 1.0, 1.0], metadata=check(
        lambda v: len(v) == 3 and all(0.2 <= x <= 5 for x in v), "[r, g, b] gains in 0.2..5"))
    """The camera's gain per channel on linear light."""
    gain_noise: float = field(default=0.0, metadata=within(0, 0.5))
    """Shot noise of the light times the gain: its standard deviation on linear light at full
    scale and exposure 1 (it grows with the square roots of the signal and the exposure)."""
    vignetting: float = field(default=0.0, metadata=within(0, 1))
    """How much darker the frame's corners are than its centre (0.3: 30 %)."""
    motion_blur: float = field(default=0.0, metadata=within(0, 0.2, " s"))
    """The shutter time over which the robot's turning and driving smear the frame."""


@dataclass
class SimConfig(SimFaults, LookKnobs, SimKnobs):
    """The ``[sim]`` section: the user's knobs, then the fault injection keys."""


FAULT_KEYS = tuple(f.name for f in dataclasses.fields(SimFaults))


def randomized_knobs() -> list[tuple[str, Randomized]]:
    """Each randomized ``[sim]`` knob and its range, in ``SimConfig``'s order (the order of
    the draws)."""
    return [(f.name, f.metadata["randomize"]) for f in dataclasses.fields(SimConfig)
            if "randomize" in f.metadata]


@dataclass
class RandomizeOwn:
    """Per-episode ranges for the [sim] knobs (docs/SIM.md, "Domain randomization"). A
    "factor" range multiplies the [sim] value; the others are the value itself. The keys below
    are the section's own; each knob's range is declared beside the knob (``SimKnobs``)."""

    enabled: Optional[bool] = None
    """On or off for every env and for `jetbot-rt run` (one draw from [sim] seed);
    default: the task decides (forward: off), and `jetbot-rt run` is off."""
    floor_plain: float = field(default=0.3, metadata=within(0.0, 1.0))
    """Probability that an episode's floor is plain (every tile one colour) instead of
    ``[sim] floor_texture``'s checker: real floors are rarely a checker board."""
    plain_floor_grey: List[float] = field(
        default_factory=lambda: [0.15, 0.8], metadata=low_high(0, 1)
    )
    """A plain floor's colour: this grey level, then each channel times ``plain_floor_tint``
    (carpets, linoleum, wood: any hue, dark or light)."""
    plain_floor_tint: List[float] = field(
        default_factory=lambda: [0.7, 1.3], metadata=low_high(0, 5)
    )
    """Factor on each channel of a plain floor apart; red at most 1 (never redder than grey:
    the goal is the red block)."""
    tint: List[float] = field(default_factory=lambda: [0.85, 1.15], metadata=low_high(0, 5))
    """Factor on each channel of each colour apart: a shift of hue."""
    deadband_lift: Optional[List[float]] = field(default=None, metadata=low_high(-0.3, 0.3))
    """A calibrated robot: each episode's ``[actions] deadband`` lift is its drawn dead-band
    plus a draw from this range (the calibration's error), at least 0; unset: the lift is
    ``[actions] deadband``. Drawn after every other draw, so a seeded reset's world is as
    without it."""


TRAINING_FLOORS = ("checker", "plain", "wood", "tiles", "concrete")
"""The floor families a training draw uses by default; carpet and rug are held out."""
HELDOUT_FLOOR_HSV = (28.0, 40.0, 0.4, 0.6, 0.35, 0.55, 200.0, 230.0, 0.25, 0.5, 0.3, 0.5)
"""Two colour boxes no training floor is drawn in (hue degrees, saturation, value: low, high
each): a mid oak brown and a dark blue-grey."""


def _families(choices: tuple[str, ...]) -> dict[str, Any]:
    return check(lambda v: len(v) > 0 and all(x in choices for x in v),
                 "a non-empty list of " + ", ".join(repr(c) for c in choices))


def _hsv_boxes(v: List[float]) -> bool:
    boxes = [v[i:i + 6] for i in range(0, len(v), 6)]
    return len(v) % 6 == 0 and all(
        0 <= h0 <= h1 <= 360 and 0 <= s0 <= s1 <= 1 and 0 <= v0 <= v1 <= 1
        for h0, h1, s0, s1, v0, v1 in boxes)


@dataclass
class RandomizeLook:
    """Per-episode draws of the appearance families (``[sim]``'s ``LookKnobs``, the floor's
    family and colour, the walls' colours); only with ``appearance = true``, after every
    other draw, so that without it every seed draws what it drew before."""

    appearance: bool = True
    """Draw the appearance families per episode (docs/SIM.md, "Appearance families")."""
    floor_families: List[str] = field(default_factory=lambda: list(TRAINING_FLOORS),
                                      metadata=_families(FLOOR_TEXTURES))
    """The floor families drawn, each as likely (the rest are held out for evaluation)."""
    heldout_floor_hsv: List[float] = field(default_factory=lambda: list(HELDOUT_FLOOR_HSV),
                                           metadata=check(_hsv_boxes, (
                                               "boxes of 6 numbers: hue low, high (degrees), "
                                               "saturation low, high, value low, high (0..1)")))
    """Colour boxes no floor is drawn in (held out for evaluation)."""
    floor_saturation: List[float] = field(default_factory=lambda: [0.0, 0.5],
                                          metadata=low_high(0, 1))
    """A floor's colour: any hue, this saturation (near the goal's red at most 0.31), ..."""
    floor_value: List[float] = field(default_factory=lambda: [0.15, 0.9],
                                     metadata=low_high(0, 1))
    """... and this value (HSV)."""
    wall_textures: List[str] = field(default_factory=lambda: list(WALL_TEXTURES),
                                     metadata=_families(WALL_TEXTURES))
    home_walls: float = field(default=0.7, metadata=within(0.0, 1.0))
    """Probability that the four walls are one home colour (pale, any hue) instead of the
    heading colours' tinted draw."""
    skirting: float = field(default=0.7, metadata=within(0.0, 1.0))
    """Probability of a skirting board (white, wood or grey)."""
    clutter: List[float] = field(default_factory=lambda: [0, 6], metadata=low_high(0, 12))
    lamps: List[float] = field(default_factory=lambda: [0, 3], metadata=low_high(0, 4))
    window_light: List[float] = field(default_factory=lambda: [0.0, 1.0],
                                      metadata=low_high(0, 2))
    light_temperature: List[float] = field(default_factory=lambda: [2700.0, 6500.0],
                                           metadata=low_high(1000, 12000, " K"))
    """The renderer light's colour: a black body at this temperature."""
    shadows: float = field(default=0.5, metadata=within(0.0, 1.0))
    """Probability that the light casts shadows."""
    exposure: List[float] = field(default_factory=lambda: [0.6, 1.6], metadata=low_high(0.05, 8))
    """Drawn log-uniformly."""
    white_balance: List[float] = field(default_factory=lambda: [0.85, 1.15],
                                       metadata=low_high(0.2, 5))
    """Red and blue gains (green 1)."""
    gain_noise: List[float] = field(default_factory=lambda: [0.0, 0.03], metadata=low_high(0, 0.5))
    vignetting: List[float] = field(default_factory=lambda: [0.0, 0.5], metadata=low_high(0, 1))
    motion_blur: List[float] = field(default_factory=lambda: [0.0, 0.02],
                                     metadata=low_high(0, 0.2, " s"))


def _range_field(spec: Randomized) -> tuple[Any, Any]:
    hint = Optional[List[float]] if spec.optional else List[float]
    return hint, field(default_factory=lambda: list(spec.default),
                       metadata=low_high(spec.low, spec.high, spec.unit))


RandomizeConfig = dataclasses.make_dataclass(
    "RandomizeConfig",
    [(spec.key or name, *_range_field(spec)) for name, spec in randomized_knobs()],
    bases=(RandomizeOwn, RandomizeLook),
    namespace={"__doc__": RandomizeOwn.__doc__, "__module__": __name__},
)
"""``[randomize]``: ``RandomizeOwn``'s keys and one ``[low, high]`` range per randomized knob."""
