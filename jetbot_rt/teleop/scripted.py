"""``--input scripted``: the simulator's stand-in for a person, and the sim's episodes.

The person is the task's privileged expert (the DAgger teacher: it reads the simulator's
state, never the image), driving through the same path as a keyboard: it proposes a
``HandCommand`` each tick, which the ``Arbiter``, the action pipeline and the latch treat as
any hand command. What makes it a person rather than the teacher:

- **Reaction time** ``REACTION_S`` (0.2 s of simulated time): the command applied now is the
  one the expert chose for the state 0.2 s ago; a take-over decision waits as long.
- **Noise**: ``NOISE`` (standard deviation 0.1 on each wheel's command, -1..1) while it
  drives; none while it holds still (a person who stops lets go of the keys).
- **Take-over rule** (with ``--policy``, goal tasks): it takes over when the policy is off by
  ``HEADING_OFF_DEG`` (the goal 25 degrees or more off the robot's heading and the error grown
  by ``HEADING_GROWTH_DEG`` in the last 0.5 s: turning away), by progress (the distance to the
  goal down by less than ``PROGRESS_M`` = 2 cm in ``PROGRESS_S`` = 1.5 s while more than 5 cm
  beyond the stop point: stalled or circling), or arrives too fast (within 2 cm of the stop
  point at more than ``OVERSHOOT_SPEED`` = 0.05 m/s: it would push the goal). It hands back
  once corrected: after at least ``MIN_TAKEOVER_S`` = 1 s, with the goal within
  ``CORRECTED_DEG`` = 10 degrees of the heading and none of the rules holding.

Times are simulated time, so a recording replays the same decisions whatever the machine's
load.
"""

from __future__ import annotations

import collections
import math
from typing import Any

import numpy as np

from jetbot_rt.errors import UsageError
from jetbot_rt.teleop.hand import HandCommand, HandInput

REACTION_S = 0.2
NOISE = 0.1
HEADING_OFF_DEG = 25.0
HEADING_GROWTH_DEG = 3.0
HEADING_WINDOW_S = 0.5
PROGRESS_M = 0.02
PROGRESS_S = 1.5
STALL_MARGIN_M = 0.05
OVERSHOOT_M = 0.02
OVERSHOOT_SPEED = 0.05
MIN_TAKEOVER_S = 1.0
CORRECTED_DEG = 10.0
SUCCESS_HOLD_S = 1.0
"""A drive episode ends this long after its task's success began (or at its end, failure or
time limit): a few frames of standing at the goal, then a new scene."""


def world_info(task: Any, world: Any) -> dict[str, Any]:
    """The env's ``info`` for the world as it is (the task's outcome, the pose, the time)."""
    return {**task.outcome(world.scene, world), "pose": np.array(world.robot_pose()),
            "sim_time": world.sim_time}


class ScriptedInput(HandInput):
    name = "scripted"

    def __init__(self, task: Any, with_policy: bool, seed: int = 0) -> None:
        super().__init__()
        expert = task.expert()
        if expert is None:
            raise UsageError(f"--input scripted: task {task.name!r} has no privileged expert "
                             "to stand in for a person")
        self.task = task
        self.expert = expert
        self.with_policy = with_policy
        self.rng = np.random.default_rng(seed)
        self.world: Any = None
        self.reset()

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "reaction_s": REACTION_S, "noise": NOISE,
                "takeover": {"heading_off_deg": HEADING_OFF_DEG,
                             "progress_m": PROGRESS_M, "progress_s": PROGRESS_S,
                             "overshoot_speed": OVERSHOOT_SPEED,
                             "min_takeover_s": MIN_TAKEOVER_S, "corrected_deg": CORRECTED_DEG}}

    def bind(self, world: Any) -> None:
        """The simulated world it reads (after the robot connected)."""
        info = world_info(self.task, world)
        if self.with_policy and not {"goal_xy", "distance"} <= info.keys():
            raise UsageError(f"--input scripted with --policy: the take-over rule needs a goal "
                             f"task (forward, seek); {self.task.name!r} has no goal")
        self.world = world

    def reset(self) -> None:
        """A new episode: nothing seen yet, nothing taken over."""
        self.pending: collections.deque[tuple[float, np.ndarray, bool, bool]] = collections.deque()
        self.history: collections.deque[tuple[float, float, float]] = collections.deque()
        self.taking = False
        self.since = 0.0
        self._last: HandCommand | None = None

    def command(self, now: float) -> HandCommand | None:
        """Called by the arbiter on the control thread, once per tick (``now`` unused: the
        person lives in simulated time)."""
        if self.world is None:
            return None
        info = world_info(self.task, self.world)
        t = float(info["sim_time"])
        label = np.asarray(self.expert.label(info), dtype=np.float64)
        off, corrected = self._judge(info, t) if self.with_policy else (False, True)
        self.pending.append((t, label, off, corrected))
        acting = None
        while self.pending and self.pending[0][0] <= t - REACTION_S + 1e-9:
            acting = self.pending.popleft()
        if acting is None:  # not reacted yet: what it did before holds
            return self._last if self.taking or not self.with_policy else None
        _, label, off, corrected = acting
        if self.with_policy:
            if not self.taking and off:
                self.taking, self.since = True, t
            elif self.taking and t - self.since >= MIN_TAKEOVER_S and corrected:
                self.taking = False
            if not self.taking:
                return None
        if np.any(label != 0.0):
            label = np.clip(label + self.rng.normal(0.0, NOISE, 2), -1.0, 1.0)
        self._last = HandCommand((float(label[0]), float(label[1])), takeover=True)
        return self._last

    def _judge(self, info: dict[str, Any], t: float) -> tuple[bool, bool]:
        """(the policy is off, the state is corrected) by the rules in the module's doc."""
        x, y, yaw = (float(v) for v in info["pose"])
        gx, gy = (float(v) for v in info["goal_xy"])
        error = math.atan2(gy - y, gx - x) - yaw
        error = abs(math.degrees(math.atan2(math.sin(error), math.cos(error))))
        distance = float(info["distance"])
        speed = float(info.get("speed", 0.0))
        stop = float(getattr(self.expert, "stop_distance", 0.12))
        self.history.append((t, distance, error))
        while self.history and self.history[0][0] < t - PROGRESS_S - 1e-9:
            self.history.popleft()
        heading_before = next((e for (s, _, e) in self.history if s >= t - HEADING_WINDOW_S),
                              error)
        turning_away = error >= HEADING_OFF_DEG and error - heading_before >= HEADING_GROWTH_DEG
        first_t, first_d, _ = self.history[0]
        stalled = (t - first_t >= PROGRESS_S - 1e-6 and distance > stop + STALL_MARGIN_M
                   and first_d - distance < PROGRESS_M)
        overshoot = distance < stop + OVERSHOOT_M and speed > OVERSHOOT_SPEED
        off = turning_away or stalled or overshoot
        return off, (error < CORRECTED_DEG or distance <= stop + OVERSHOOT_M) and not off


class SimEpisodes:
    """The sim's episodes while driving: after each tick, the task's outcome; at its end
    (the task's ``terminated``, ``SUCCESS_HOLD_S`` after success began, or the time limit) a
    new scene from the task's generator seeded with ``(seed, episode)``, the robot with its
    start noise, and the ``[sim]`` knobs drawn again when ``[randomize]`` is on."""

    def __init__(self, robot: Any, task: Any, config: Any, on_end: Any) -> None:
        self.robot = robot
        self.world = robot.world
        self.task = task
        self.config = config
        self.on_end = on_end
        self.episode = 0
        self.steps = 0
        self.success_since: float | None = None
        self.successes = 0

    def observe(self, _result: Any) -> None:
        info = world_info(self.task, self.world)
        self.steps += 1
        t = float(info["sim_time"])
        success = bool(info["is_success"])
        if success and self.success_since is None:
            self.success_since = t
        elif not success:
            self.success_since = None
        held = self.success_since is not None and t - self.success_since >= SUCCESS_HOLD_S
        if not (held or self.task.terminated(info) or self.steps >= self.task.episode_steps):
            return
        self.successes += success
        self.on_end(self.episode, success, "failed" if info.get("failed") else
                    "success" if success else "time limit", self.steps)
        self.next_scene()

    def next_scene(self) -> None:
        from jetbot_rt.sim.randomize import sample

        self.episode += 1
        self.steps = 0
        self.success_since = None
        rng = np.random.default_rng((self.config.sim.seed, self.episode))
        scene = self.task.scene(rng, True)
        sim = (sample(self.config.sim, self.config.randomize, rng)
               if self.config.randomize.enabled else None)
        self.world.reset(scene=scene, sim=sim)
        self.robot.camera.capture()
