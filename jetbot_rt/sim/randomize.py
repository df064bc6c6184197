"""Domain randomization: one draw of the ``[sim]`` knobs per episode from ``[randomize]``'s
ranges, with the caller's seeded generator (the env's ``np_random``), so ``reset(seed=...)``
reproduces the episode, parameters and pixels alike.

The draw is a complete ``SimConfig``: ``sim_toml(sim)`` writes it as a ``[sim]`` table that
``jetbot-rt run --backend sim --config`` and ``jetbot-train eval --config`` replay.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from jetbot_rt.config.schema import set_value
from jetbot_rt.errors import UsageError
from jetbot_rt.sim.appearance import wall_colors
from jetbot_rt.sim.config import RandomizeConfig, Randomized, SimConfig, randomized_knobs
from jetbot_rt.sim.look_draws import LOOK_KEYS, sample_looks
from jetbot_rt.sim.look_draws import plain_float as _r

_KNOBS = (*(name for name, _ in randomized_knobs()), "seed", "floor_texture")
DRAWN = (*_KNOBS, *(key for key in LOOK_KEYS if key not in _KNOBS))
"""The [sim] keys a draw sets (``seed`` seeds the episode's image noise; the appearance
families' keys stay at their ``[sim]`` values unless ``[randomize] appearance`` is on)."""


def _uniform(rng: np.random.Generator, bounds: list[float], size: int | None = None) -> Any:
    low, high = bounds
    return rng.uniform(low, high, size)


def _color(rng: np.random.Generator, base: list[float], factor: list[float],
           tint: list[float]) -> list[float]:
    """``base`` lighter or darker by one factor, then each channel by a tint factor."""
    factors = _uniform(rng, factor) * _uniform(rng, tint, 3)
    return [_r(min(max(c * f, 0.0), 1.0)) for c, f in zip(base, factors, strict=True)]


def sample(base: SimConfig, ranges: RandomizeConfig, rng: np.random.Generator) -> SimConfig:
    """``base`` with every randomized knob drawn from ``ranges`` (always in the same order:
    the draw depends on the generator's state only)."""
    r = ranges
    # the knobs drawn by code of their own ("custom"), first
    gains = _uniform(rng, r.wheel_gain, 2)
    azimuth = rng.uniform(-math.pi, math.pi)
    elevation = math.radians(_uniform(rng, r.light_elevation_deg))
    stall = _uniform(rng, r.stall_torque) if r.stall_torque is not None else None
    walls = [c for rgb in wall_colors(base) for c in _color(rng, list(rgb), r.wall_color, r.tint)]
    custom: dict[str, Any] = {
        "wheel_gain": [_r(min(base.wheel_gain[i] * gains[i], 2.0)) for i in (0, 1)],
        "stall_torque": _r(stall) if stall is not None else base.stall_torque,
        "wall_color": walls,
        "light_direction": [
            _r(math.cos(elevation) * math.cos(azimuth)),
            _r(math.cos(elevation) * math.sin(azimuth)),
            _r(math.sin(elevation)),
        ],
    }
    def draw(name: str, spec: Randomized) -> Any:
        bounds = getattr(r, spec.key or name)
        if spec.draw == "custom":
            return custom[name]
        if spec.draw == "factor":
            return _r(getattr(base, name) * _uniform(rng, bounds))
        if spec.draw == "offset":
            return _r(getattr(base, name) + _uniform(rng, bounds))
        if spec.draw == "color":
            return _color(rng, getattr(base, name), bounds, r.tint)
        return _r(_uniform(rng, bounds))

    drawn: dict[str, Any] = {}
    for name, spec in randomized_knobs():  # then every other knob, in SimConfig's order
        if not spec.late:
            drawn[name] = draw(name, spec)
    drawn["seed"] = int(rng.integers(2**31))
    # drawn last, so that adding them left every earlier draw of a seed as it was
    plain = rng.random() < r.floor_plain
    grey = _uniform(rng, r.plain_floor_grey)
    hue = _uniform(rng, r.plain_floor_tint, 3)
    hue[0] = min(hue[0], 1.0)
    drawn["floor_texture"] = "plain" if plain else base.floor_texture
    if plain:
        drawn["floor_color"] = [_r(min(grey * h, 1.0)) for h in hue]
    for name, spec in randomized_knobs():
        if spec.late:
            drawn[name] = draw(name, spec)
    if r.appearance:  # the families, after everything: without them a seed draws as before
        drawn.update(sample_looks(base, r, rng))
    out = dataclasses.replace(base)
    for key, value in drawn.items():  # a draw must be a valid [sim] table (replayable)
        try:
            set_value(out, "sim", key, value)
        except UsageError as exc:
            raise UsageError(f"[randomize] drew an invalid value: {exc}") from None
    return out


def params(sim: SimConfig) -> dict[str, Any]:
    """The randomized knobs of ``sim`` as plain values (for ``info`` and reports)."""
    out = {key: getattr(sim, key) for key in DRAWN}
    return {k: list(v) if isinstance(v, list) else v for k, v in out.items()}


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def sim_toml(sim: SimConfig) -> str:
    """A ``[sim]`` TOML table holding every set key of ``sim`` (a draw, replayable)."""
    lines = ["[sim]"]
    for f in dataclasses.fields(sim):
        value = getattr(sim, f.name)
        if value is not None:
            lines.append(f"{f.name} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"
