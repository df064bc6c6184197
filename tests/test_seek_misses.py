"""benchmarks/seek_misses.py's sorting of a miss by where the robot went."""

from __future__ import annotations

import json
import sys
from types import SimpleNamespace

import numpy as np
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


def _env(lift: float) -> SimpleNamespace:
    return SimpleNamespace(unwrapped=SimpleNamespace(
        task=Seek, sim_params={"deadband": 0.28}, pipeline=SimpleNamespace(deadband=lift),
        scene=SimpleNamespace(pieces=())))


def test_a_miss_line_gives_the_last_command_the_drawn_dead_band_and_the_lift(misses):
    episode = misses.Episode(np.zeros(2), 0.8, np.array([0.7, 0.56]), np.array([0.33, 0.24]))
    info = {**_info(0.16), "pose": [0.0, 0.0, 0.0], "speed": 0.0}
    found, detail = misses.sort(_env(0.0), info, episode)
    assert found == "near the goal"
    assert detail.endswith("mean command (0.70, 0.56), last (0.33, 0.24), dead-band 0.28")
    assert misses.sort(_env(0.3), info, episode)[1].endswith("dead-band 0.28, lift 0.30")


class _CountingEnv:
    """Ends its episode at the third step; the pose moves 0.1 m a step along x."""

    def __init__(self) -> None:
        self.steps = 0

    def reset(self, seed: int) -> tuple[int, dict]:
        self.steps = 0
        return 0, {"pose": [0.0, 0.0, 0.0]}

    def step(self, command: np.ndarray) -> tuple[int, float, bool, bool, dict]:
        self.steps += 1
        return self.steps, 0.0, self.steps == 3, False, {"pose": [0.1 * self.steps, 0.0, 0.0]}


def test_a_replay_keeps_the_last_command_and_the_farthest_point(monkeypatch):
    replay = load_script("benchmarks/replay_misses.py", monkeypatch).replay
    policy = SimpleNamespace(infer=lambda obs: np.array([0.1 * obs, -0.1 * obs]))
    _, episode = replay(_CountingEnv(), policy, seed=1)
    assert episode.last_command == pytest.approx([0.2, -0.2])  # the command at obs 2
    assert episode.mean_command == pytest.approx([0.1, -0.1])
    assert episode.farthest == pytest.approx(0.3)


def test_a_replay_with_another_lift_than_its_evaluation_is_refused(monkeypatch, tmp_path, capsys):
    replay_misses = load_script("benchmarks/replay_misses.py", monkeypatch)
    evaluation = tmp_path / "heldout.json"
    evaluation.write_text(json.dumps({"seed": 20000, "episodes": 2, "successes": [],
                                      "deadband_lift": [-0.05, 0.05]}))
    monkeypatch.setattr(sys, "argv", ["seek_misses.py", "--policy", "p.onnx",
                                      "--eval", str(evaluation)])
    with pytest.raises(SystemExit) as stopped:
        replay_misses.open_replay("seek", "doc")
    assert stopped.value.code == 2
    assert "pass the --config the evaluation ran with" in capsys.readouterr().err


def test_the_stops_summary_counts_the_stops_that_crowd_the_threshold(monkeypatch):
    stops = load_script("benchmarks/seek_stops.py", monkeypatch)
    line = stops.summary([0.10, 0.12, 0.141, 0.149], 0.15)
    assert line.startswith("4 successes: final distance min 0.100")
    assert line.endswith("max 0.149 m; 2 within 1 cm of 0.15 m")
    assert stops.summary([0.12], 0.15, failed_now=3).endswith("of 0.15 m; 3 failed now")
    assert stops.summary([], 0.15) == "no successes"
    assert stops.summary([], 0.15, failed_now=2) == "no successes; 2 failed now"
