"""The privileged teacher of goal tasks (seek): a scripted controller that reads the
simulator's true state (the robot's pose and speed, the goal's position; never the image) and
drives to the goal.

DAgger labels every frame the student sees with this controller's action. It is closed loop on
the state, so the randomized wheel gains, dead-band and latencies need no model: a weak wheel
shows as a bearing error that it turns away, a late stop as speed that moves the stop point
out. Why these numbers: docs/TRAINING.md ("Training seek by DAgger").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class GoalExpert:
    stop_distance: float = 0.12
    """m, axle to the goal's centre: command zero from here on. Success needs < 0.15 m; the
    robot coasts on after the zero command (0.2-2.7 cm in the randomized episodes:
    ``benchmarks/bench_expert_choices.py``), touching the block at most without pushing it
    3 cm. Why 3 cm inside 0.15 m: the student's stop is blurred over a few cm (the randomized
    camera mount moves the block's picture), and with 2 cm of margin most of its misses were
    stalls just outside 0.15 m on dead-band robots."""
    stop_lead: float = 0.0
    """s; moves the stop point out by speed * this. 0: the stop is a function of where the
    block is, which the camera shows; speed a single frame hardly shows, and a stop that
    depends on it gave the student contradictory labels (it stalled 2-4 cm short)."""
    turn_gain: float = 2.5
    """Turn command per rad of bearing error."""
    forward_gain: float = 4.0
    """Forward command per m beyond the stop point."""
    search_bearing_deg: float = 40.0
    """Beyond this bearing error the expert searches: turns left (``search_left``,
    ``search_right``), whichever side the goal is on. The fisheye shows 49 degrees either
    side at the policy's size: 40 leaves the goal's picture in view where the labels say
    "turn toward it" (a student that sees only the frame cannot know the side of a goal out of
    view, and labels that said "turn toward it" there averaged to zero: it stalled). Through
    the pinhole (34 degrees at the narrowest randomized field of view) use 30 (the DAgger
    option ``--search-bearing-deg``). With 150 ms motor plus 100 ms camera latency and the
    expert acting on what the frame shows, 30 overshot the goal out of the tracking band,
    sent the search round the whole circle and succeeded in 37 of 100 episodes; 40 with the
    slower search below, 99 of 100 (benchmarks/bench_expert_choices.py)."""
    search_left: float = -0.6
    """The search's left wheel command."""
    search_right: float = 0.2
    """The search's right wheel command: with the left wheel's -0.6 a turn to the left that
    backs away (a spin in place, (-1, 1), would sweep the robot's front into a block that
    sits too close to be seen); slow enough that 250 ms of latency stops it inside the
    tracking band (at (-1, 0.3) it swept past)."""
    min_forward: float = 0.75
    """The slowest forward command while driving: the dead-band (up to 0.3 of duty) eats
    0.6 of the command at max_speed 0.5, so less would stall."""
    backoff_distance: float = 0.10
    """m; closer than this the expert backs away at ``backoff`` instead of waiting (0:
    never). A robot that coasts this far (latency, a fast robot) has the block slipping below
    the camera's view (a sliver of red at 0.10 m), a frame a student took for "goal out of
    view": it searched, and pushed the block. Taught to back away there, it does not. 2 cm
    inside ``stop_distance``: the band where it waits is 2 cm wide."""
    backoff: float = -0.3
    """The command of both wheels while backing away: slow, so that it stops again before
    the stop distance (at -0.8 the expert itself hunted back and forth under latency)."""

    reads: tuple[str, ...] = ("pose", "goal_xy", "speed")
    """The env's info keys ``label`` reads."""

    def label(self, info: dict[str, Any]) -> np.ndarray:
        return self.act(info["pose"], info["goal_xy"], float(info["speed"]))

    def act(self, pose: np.ndarray, goal_xy: np.ndarray, speed: float) -> np.ndarray:
        """``[left, right]`` in [-1, 1] for one robot."""
        x, y, yaw = (float(v) for v in pose)
        dx, dy = float(goal_xy[0]) - x, float(goal_xy[1]) - y
        distance = math.hypot(dx, dy)
        error = math.atan2(dy, dx) - yaw
        error = math.atan2(math.sin(error), math.cos(error))
        beyond = distance - (self.stop_distance + self.stop_lead * speed)
        if distance < self.backoff_distance:
            return np.full(2, self.backoff, dtype=np.float32)
        if beyond <= 0.0:
            return np.zeros(2, dtype=np.float32)
        if abs(error) > math.radians(self.search_bearing_deg):
            return np.array([self.search_left, self.search_right], dtype=np.float32)
        turn = float(np.clip(self.turn_gain * error, -1.0, 1.0))
        forward = float(np.clip(self.forward_gain * beyond, self.min_forward, 1.0))
        forward *= max(math.cos(error), 0.0)
        left, right = forward - turn, forward + turn
        return np.clip(np.array([left, right], dtype=np.float32), -1.0, 1.0)
