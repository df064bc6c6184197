"""The ``sim`` backend: a ``Camera`` and a ``Drive`` over one ``JetbotWorld``.

The loop calls ``SimRobot.step(dt)`` once per tick, after the drive write and outside the
tick's timing: the world steps one control period and the camera renders the frame the next
tick will read. The
camera's fault injection (``[sim] camera_stall_after``, ``[sim] blackout``) runs on simulated
time, so a run with faults replays identically.

A frame's age (``[loop] max_frame_age``) is simulated time too: what the limit guards against
is the world moving on while the policy looks at an old image, and a simulated world stands
still while the process is not scheduled (a desktop's hiccup is no stale frame here). A frozen
camera (``camera_stall_after``) still ages one period per tick.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from jetbot_rt.errors import UsageError
from jetbot_rt.hal.base import Camera, Drive, Frame, Robot
from jetbot_rt.sim.randomize import sample
from jetbot_rt.sim.world import JetbotWorld
from jetbot_rt.tasks import DEFAULT_TASK, load_task
from jetbot_rt.tasks.loader import is_code_reference

if TYPE_CHECKING:
    from jetbot_rt.config.sections import Config
    from jetbot_rt.hal.registry import BackendOptions
    from jetbot_rt.sim.config import SimConfig


@dataclass(frozen=True)
class SimFrame(Frame):
    """A rendered frame and the simulated time at which it was rendered."""

    sim_time: float = 0.0


class SimCamera(Camera):
    """The robot's camera. ``read()`` returns the newest rendered frame without rendering;
    ``capture()`` (called by the backend after each world step) renders the next one."""

    def __init__(self, world: JetbotWorld, sim: SimConfig) -> None:
        self._world = world
        self._stall_after = sim.camera_stall_after
        self._blackout = sim.blackout
        self._frame: SimFrame | None = None
        self._count = 0
        self._running = False

    def start(self) -> None:
        self._running = True
        self.capture()

    def capture(self) -> None:
        """Render a new frame at the world's current state, unless a fault says otherwise."""
        if not self._running:
            return
        t = self._world.sim_time
        if self._frame is not None and self._stall_after is not None and t > self._stall_after:
            return  # stalled: the last frame stays, and goes stale
        if self._blackout is not None and self._blackout[0] <= t <= self._blackout[1]:
            image = np.zeros((self._world.image_size[1], self._world.image_size[0], 3), np.uint8)
        else:
            image = self._world.frame()
        self._count += 1
        self._frame = SimFrame(image, time.monotonic(), self._count, t)

    def read(self) -> Frame | None:
        return self._frame if self._running else None

    def frame_age(self, frame: Frame, now: float) -> float:
        """Simulated seconds since ``frame`` was rendered (``now``, wall time, is not used)."""
        if isinstance(frame, SimFrame):
            return self._world.sim_time - frame.sim_time
        return super().frame_age(frame, now)

    def stop(self) -> None:
        self._running = False


class SimDrive(Drive):
    """Duties go to the world's motor model; they take effect at the next world step."""

    def __init__(self, world: JetbotWorld) -> None:
        self._world = world

    def write(self, left: float, right: float) -> None:
        self._world.set_duty(left, right)  # a non-finite duty raises NonFinite, a Fault

    def stop(self) -> None:
        self._world.set_duty(0.0, 0.0)


class SimRobot(Robot):
    """The robot in a ``JetbotWorld``: ``step(dt)`` steps the world one control period and
    renders the frame the next tick will read."""

    simulated = True

    def __init__(self, world: JetbotWorld, sim: SimConfig) -> None:
        self._sim_camera = SimCamera(world, sim)
        super().__init__(self._sim_camera)
        self._world = world
        # What the robot did, kept up to date here: the summary is built after the world closed.
        # The distance to the piece named "goal", in scenes that have one.
        self._travelled_m = 0.0
        self._goal_distance_m = self._goal_distance()

    @property
    def world(self) -> JetbotWorld:
        """The world this robot drives in (the calibration places its marker in it)."""
        return self._world

    def _goal_distance(self) -> float | None:
        world = self._world
        return world.distance("goal") if world.has_piece("goal") else None

    def open_drive(self) -> Drive:
        return SimDrive(self._world)

    def step(self, dt: float) -> None:
        world = self._world
        x0, y0, _ = world.robot_pose()
        world.step(dt)
        x1, y1, _ = world.robot_pose()
        self._travelled_m += math.hypot(x1 - x0, y1 - y0)
        self._goal_distance_m = self._goal_distance()
        self._sim_camera.capture()

    def state(self) -> dict[str, object]:
        state: dict[str, object] = {"pose": list(self._world.robot_pose()),
                                    "sim_time": self._world.sim_time}
        if self._goal_distance_m is not None:
            state["goal_distance"] = self._goal_distance_m
            x, y, _ = self._world.position("goal")
            state["goal"] = [round(x, 3), round(y, 3)]
        return state

    def stats(self) -> dict[str, float]:
        stats = {"travelled_m": round(self._travelled_m, 3)}
        if self._goal_distance_m is not None:
            stats["goal_distance_m"] = round(self._goal_distance_m, 3)
        return stats

    def disconnect(self) -> None:
        self.camera.stop()
        self._world.close()


def scene_task(config: Config, options: BackendOptions) -> str:
    """The task whose scene to build: ``[sim] task``, else the policy's metadata, else
    forward. A policy file names its task but is no one's command to run code: a metadata
    task that is a file or module (``X:Class``) is refused; ``[sim] task`` may name one."""
    if config.sim.task:
        return config.sim.task
    named = options.task
    if named and is_code_reference(named):
        raise UsageError(f"the policy's task {named!r} is code in a file or module; to run "
                         "it, name it yourself: [sim] task = \"...\" in the config")
    return named or DEFAULT_TASK


def build_backend(config: Config, options: BackendOptions) -> Robot:
    """The world in the scene of the policy's task (``scene_task``) drawn with ``[sim]
    seed``, the robot at the task's nominal pose -- the env's ``reset(seed=seed,
    options={"start_noise": False})`` --, rendering at the policy's frame size. With
    ``[randomize] enabled = true`` the [sim] knobs are drawn once, from the same seeded
    generator after the scene (as the env does)."""
    task = load_task(scene_task(config, options))
    rng = np.random.default_rng(config.sim.seed)
    scene = task.scene(rng, False)
    world = JetbotWorld(config.sim, gui=options.gui, image_size=tuple(options.frame_size))
    world.reset(scene=scene, sim=sample(config.sim, config.randomize, rng)
                if config.randomize.enabled else None)
    return SimRobot(world, config.sim)
