"""What ``jetbot-rt report`` draws: the stretches a person drove, and a stop the run chose
drawn grey, not as a red fault (the map of a real sim run: tests/test_record.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from jetbot_rt.commands import report
from jetbot_rt.recording.reader import Recording

RATE_HZ = 30.0
TICKS = 45
HUMAN_TICKS = range(15, 25)
GOAL = [0.6, 0.4]


def telemetry(path: Path) -> Path:
    """A sim-like run's telemetry: an arc towards GOAL, a person driving ticks 15-24."""
    lines = []
    for tick in range(1, TICKS + 1):
        angle = tick / TICKS * math.pi / 2
        lines.append({"t": tick / RATE_HZ, "tick": tick, "state": "driving", "mu": [0.5, 0.4],
                      "cmd": [0.05, 0.04], "frame_age_ms": 1.0, "infer_ms": 1.0,
                      "tick_ms": 2.0, "overruns": 0,
                      "pose": [0.5 * math.sin(angle), 0.5 * (1 - math.cos(angle)), angle],
                      "goal": GOAL, "driver": "human" if tick in HUMAN_TICKS else "policy"})
    lines.append({"t": TICKS / RATE_HZ, "event": "safe_stop", "fault": False,
                  "reason": "duration 1.5 s reached", "cmd": [0.0, 0.0]})
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    return path


def test_the_video_marks_a_fault_red_and_an_orderly_stop_grey() -> None:
    image = np.full((56, 56, 3), 90, np.uint8)
    record = {"t": 1.0, "tick": 30, "mu": [0.5, 0.4], "cmd": [0.05, 0.04], "tick_ms": 2.0,
              "infer_ms": 1.0, "frame_age_ms": 1.0, "overruns": 0, "driver": "human"}
    fault = report.compose(image, record, 0.1, {"event": "safe_stop", "fault": True})
    orderly = report.compose(image, record, 0.1, {"event": "safe_stop", "fault": False})
    assert list(fault[2, 200]) == [0, 0, 255]
    assert list(orderly[2, 200]) == [200, 200, 200]


def test_the_ticks_a_person_drove_are_one_span_and_events_say_so_without_ticks(
        tmp_path: Path) -> None:
    rec = Recording.open(telemetry(tmp_path / "t.jsonl"))
    [(start, end)] = report.human_spans(rec)
    assert (start, end) == pytest.approx((15 / RATE_HZ, 25 / RATE_HZ), abs=1e-6)
    for record in rec.ticks:
        del record["driver"], record["pose"]
    assert report.human_spans(rec) == [], "no driver, no takeover events: nobody drove"
    assert report.positions(rec.ticks) is None, "no pose (the robot's run): no map"
    rec.records.append({"t": 0.2, "event": "takeover"})
    rec.records.append({"t": 0.4, "event": "handback"})
    assert report.human_spans(rec) == [(0.2, 0.4)]
