"""benchmarks/seek_misses.py's sorting of a miss by where the robot went."""

from __future__ import annotations

import pytest
from script_module import load_script


@pytest.fixture
def misses(monkeypatch):
    return load_script("benchmarks/seek_misses.py", monkeypatch)


class Seek:
    success_distance = 0.15


def _info(distance: float, failed: bool = False) -> dict:
    return {"is_success": False, "failed": failed, "distance": distance}


def test_a_robot_that_never_left_its_start_stayed_though_its_goal_was_near(misses):
    # a goal may be drawn 0.35 m from the start: never moving ends "near" it
    assert misses.kind(_info(0.36), Seek, distractor=0.5, farthest=0.05) == "stayed at the start"
    assert misses.kind(_info(0.36), Seek, distractor=0.5, farthest=0.6) == "near the goal"


def test_each_kind_of_miss(misses):
    assert misses.kind(_info(0.1, failed=True), Seek, 0.5, 0.8) == "pushed"
    assert misses.kind(_info(0.1), Seek, 0.5, 0.8) == "at the goal, moving"
    assert misses.kind(_info(0.7), Seek, 0.1, 0.8) == "at a distractor"
    assert misses.kind(_info(0.2), Seek, 0.1, 0.8) == "at a distractor"  # nearer it
    assert misses.kind(_info(0.9), Seek, 0.6, 0.8) == "elsewhere"
    # a robot that drove out and came back did leave its start
    assert misses.kind(_info(0.9), Seek, 0.6, farthest=0.5) == "elsewhere"
