"""The path a calibration was fitted from is shown in the output's first comment line; a path
may hold a line break or bytes that are not UTF-8, and neither may reach the TOML as such."""

from __future__ import annotations

import os

import tomllib

from jetbot_rt.calibration.intrinsics import Fit, Lens
from jetbot_rt.calibration.intrinsics import to_toml as intrinsics_toml
from jetbot_rt.commands.calibrate import comment_text


def _fit() -> Fit:
    return Fit(Lens(1.0, (0.5, 0.5), (0.01, 0.0, 0.0, 0.0)), 1.0, 1.0, 0.2, 12, (640, 360),
               (0.001, 0.001, 0.001, 0.001), 0.002)


def test_a_line_break_in_the_source_path_adds_no_toml_line() -> None:
    planted = "views\n[sim]\nmotor_gain = 9\n[randomize]\nenabled = true"
    text = intrinsics_toml(_fit(), comment_text(planted))
    assert tomllib.loads(text) == tomllib.loads(intrinsics_toml(_fit(), "views"))
    assert "views\\n[sim]\\nmotor_gain = 9" in text.splitlines()[0]


def test_a_source_path_that_is_not_utf8_is_written_as_escapes() -> None:
    name = os.fsdecode(b"views-\xff\xfe")
    shown = comment_text(name)
    assert shown == "views-\\xff\\xfe"
    intrinsics_toml(_fit(), shown).encode("utf-8")  # a lone surrogate would raise here
