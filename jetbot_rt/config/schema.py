"""The schema engine: a config section is a dataclass whose fields are its keys; a key's type is
its annotation (read with ``typing.get_type_hints``), its range or choices the field's metadata.
``set_value`` checks one key against both and says what was wrong in one line naming
``[section] key``. The owners of the sections (``config/sections.py``, ``sim/config.py``)
declare their keys with the helpers here.

The annotations of a section are written ``Optional[...]`` and ``List[...]``, not ``X | None``
and ``list[...]``: the robot's Python 3.8 evaluates them here.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from collections.abc import Callable
from typing import Any, Union

from jetbot_rt.errors import UsageError


def check(predicate: Callable[[Any], bool], expected: str) -> dict[str, Any]:
    """A key's own check and how an error names what was expected; a predicate may instead
    raise ``ValueError`` saying precisely what is wrong."""
    return {"check": predicate, "expected": expected}


def meta(*parts: dict[str, Any]) -> dict[str, Any]:
    """Several metadata parts (a check, a randomization range) as one field's metadata."""
    out: dict[str, Any] = {}
    for part in parts:
        out.update(part)
    return out


def interval(low: float, high: float | None, unit: str = "", *, open_low: bool = False,
             open_high: bool = False) -> tuple[Callable[[float], bool], str]:
    """A finite number between ``low`` and ``high`` (``None``: no upper bound), each end
    closed unless said open, and how a message writes it ("[1, 100] Hz", "(0, 1]", ">= 0")."""

    def ok(v: float) -> bool:
        if not math.isfinite(v):
            return False
        above = low < v if open_low else low <= v
        below = high is None or (v < high if open_high else v <= high)
        return above and below

    if high is None:
        return ok, f"{'>' if open_low else '>='} {low:g}{unit}"
    spelled = f"{'(' if open_low else '['}{low:g}, {high:g}{')' if open_high else ']'}{unit}"
    return ok, spelled


def within(low: float, high: float | None, unit: str = "", *, open_low: bool = False,
           open_high: bool = False, spelled: str | None = None) -> dict[str, Any]:
    """The one idiom for a numeric key: a finite number in ``interval(...)``. Every duration
    and rate is bounded, so nothing downstream sees 1e-10 Hz or a 1e10 s timeout (a thread's
    wait overflows on those). ``spelled`` writes the range in the key's own notation
    ("0x03..0x77" for an I2C address)."""
    ok, text = interval(low, high, unit, open_low=open_low, open_high=open_high)
    return check(ok, spelled or f"a number {'in ' if high is not None else ''}{text}")


def pair(low: float, high: float, *, open_low: bool = False) -> dict[str, Any]:
    """Two numbers ([left, right]), each in ``interval(low, high)``."""
    ok, text = interval(low, high, open_low=open_low)
    return check(lambda v: len(v) == 2 and all(ok(x) for x in v), f"two numbers in {text}")


def one_of(choices: tuple[str, ...]) -> dict[str, Any]:
    return check(lambda v: v in choices, "one of " + ", ".join(repr(c) for c in choices))


def rgb() -> dict[str, Any]:
    return check(lambda v: len(v) == 3 and all(0 <= x <= 1 for x in v), "[r, g, b] in 0..1")


def low_high(low: float, high: float, unit: str = "") -> dict[str, Any]:
    """A [low, high] range (for a draw) inside [``low``, ``high``]."""
    return check(
        lambda v: len(v) == 2 and low <= v[0] <= v[1] <= high,
        f"[low, high] with {low} <= low <= high <= {high}{unit}",
    )


_SCALARS: dict[Any, str] = {bool: "true or false", float: "a number", int: "an integer",
                            str: "a string"}
"""The types a key may have, and how an error names what was expected."""


def _optional(hint: Any) -> tuple[Any, bool]:
    """``Optional[X]`` -> (X, True); anything else -> (itself, False)."""
    if typing.get_origin(hint) is Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return hint, False


def type_name(hint: Any) -> str:
    """``float``, ``list[float]``: a key's type as the docs and messages write it."""
    hint, _ = _optional(hint)
    if typing.get_origin(hint) is list:
        return f"list[{type_name(typing.get_args(hint)[0])}]"
    return hint.__name__


@functools.lru_cache(maxsize=None)
def key_types(section_class: type) -> dict[str, Any]:
    """Each key of a section and its declared type, from ``typing.get_type_hints`` (the
    annotations use ``Optional``/``List``, so this works on the robot's Python 3.8 too)."""
    return typing.get_type_hints(section_class)


def _coerce(value: Any, hint: Any) -> Any:
    """A TOML value as the key's declared type, or ``TypeError`` saying what was expected."""
    hint, _ = _optional(hint)
    if typing.get_origin(hint) is list:
        (item,) = typing.get_args(hint)
        if not isinstance(value, list):
            raise TypeError(f"a list of {type_name(item)}")
        return [_coerce(v, item) for v in value]
    if hint is bool:
        ok = isinstance(value, bool)
    elif hint is float:  # an integer is a number too; true is not (bool is an int in Python)
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    elif hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, hint)
    if not ok:
        raise TypeError(_SCALARS[hint])
    return float(value) if hint is float else value


def set_value(section_obj: Any, section: str, key: str, value: Any) -> None:
    """Set one key with type and range checks; errors name ``[section] key``."""
    fields = {f.name: f for f in dataclasses.fields(section_obj)}
    if key not in fields:
        known = ", ".join(sorted(fields))
        raise UsageError(f"unknown key [{section}] {key} (known keys: {known})")
    hint = key_types(type(section_obj))[key]
    if value is None and _optional(hint)[1]:
        setattr(section_obj, key, None)
        return
    try:
        coerced = _coerce(value, hint)
    except TypeError as exc:
        raise UsageError(f"[{section}] {key} must be {exc}, got {value!r}") from None
    metadata = fields[key].metadata
    try:
        ok = "check" not in metadata or metadata["check"](coerced)
    except ValueError as exc:  # a check that says precisely what is wrong
        raise UsageError(f"[{section}] {key} must be {exc}") from None
    if not ok:
        raise UsageError(f"[{section}] {key} must be {metadata['expected']}, got {value!r}")
    setattr(section_obj, key, coerced)


