"""The Gymnasium environment: the runtime's sim world, camera and action pipeline as an Env.

A step does what one tick of ``jetbot-rt run --backend sim`` does, in the same order: the
action goes through ``ActionPipeline`` (max_speed, clamp, trim, sign), the duties to
``JetbotWorld.set_duty``, the world advances one control period, and the camera frame
rendered after that step is the next observation. ``reset`` renders the first frame.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from jetbot_rt.config.sections import Config
from jetbot_rt.errors import UsageError
from jetbot_rt.runtime.actions import ActionPipeline
from jetbot_rt.sim.config import SimConfig
from jetbot_rt.tasks import Scene, Task, load_task

POLICY_IMAGE_SIZE = 56
"""Side of the square camera image the trainer renders and its networks take (the one
source of the training size): docs/SIM.md, "The render-size seam", says why 56."""


def action_pipeline_of(config: Config, model_max_speed: float | None = None) -> ActionPipeline:
    """The pipeline the runtime builds: max_speed from config, else the model's, else 0.1."""
    return ActionPipeline.from_config(config.actions, model_max_speed)


def max_speed_of(config: Config, task: Task | None = None) -> float:
    """The duty at |mu| = 1 a task trains with: ``[actions] max_speed``, else the task's."""
    return action_pipeline_of(config, task.max_speed if task else None).max_speed


def randomizes(config: Config, task: Task, asked: bool | None = None) -> bool:
    """Whether an env of ``task`` draws its [sim] per episode: ``asked``, else ``[randomize]
    enabled``, else the task's choice."""
    if asked is not None:
        return asked
    return task.randomize if config.randomize.enabled is None else config.randomize.enabled


def calibrated_robot(config: Config, task: str | Task) -> bool:
    """Whether an env of ``config`` lifts each episode by its drawn dead-band (``[randomize]
    deadband_lift``, on an env that randomizes): a policy trained on it expects the lift."""
    return config.randomize.deadband_lift is not None and randomizes(config, load_task(task))


class JetbotEnv(gym.Env[np.ndarray, np.ndarray]):
    """Observation: the camera image, HxWx3 uint8 RGB (``image_size`` = (width, height),
    default ``POLICY_IMAGE_SIZE`` square; an evaluation passes its policy's input size).
    Action: ``[left, right]`` in [-1, 1].

    ``model_max_speed`` is the policy's metadata value, used (as by the runtime) when the
    config sets none; without either, the task's ``max_speed``. ``randomize``: draw the
    ``[sim]`` knobs from ``[randomize]`` at each reset (default: ``[randomize] enabled``,
    else the task's choice); the draw is in the reset's
    ``info["sim_params"]``. ``reset(options={"start_noise": False})`` starts exactly at the
    task's nominal pose (the blocks are still placed from the seed),
    ``options={"robot_pose": (x, y, yaw)}`` at a given one. A task with ``early_end`` ends
    (``terminated``) at its first successful step or once its goal has been pushed too far;
    every task is truncated at ``episode_steps``. ``info``: the task's ``outcome`` (for
    forward and seek ``distance``, ``block_shift``, ``speed``, ``is_success``, ``failed``,
    ``aim_error``, ``goal_xy``), then ``pose``, ``duty``, ``sim_time``.

    ``task``: a task's name (``jetbot_rt.tasks.load_task``: a built-in, ``FILE.py:Class``,
    ``module:Class``, an installed plugin's) or a ``Task``.

    ``difficulty`` (settable, also through a vector env's ``set_attr``): the task's
    ``Task.difficulty`` for the scenes of the next resets; 1 (the task as evaluated) unless
    given here or set by a curriculum.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(
        self,
        task: str | Task = "forward",
        config: Config | None = None,
        *,
        render_mode: str | None = None,
        start_noise: bool = True,
        model_max_speed: float | None = None,
        image_size: tuple[int, int] = (POLICY_IMAGE_SIZE, POLICY_IMAGE_SIZE),
        randomize: bool | None = None,
        difficulty: float = 1.0,
    ) -> None:
        from jetbot_rt.sim.world import JetbotWorld  # pybullet: only when an env is built

        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise UsageError(f"unknown render_mode {render_mode!r} (known: rgb_array)")
        self.task = load_task(task)
        self.difficulty = difficulty  # 1 unless asked: whatever a task class says
        self.config = config or Config()
        self.render_mode = render_mode
        self.start_noise = start_noise
        self.pipeline = action_pipeline_of(
            self.config, model_max_speed if model_max_speed is not None else self.task.max_speed
        )
        self._unlifted = self.pipeline
        """The pipeline of the config; a calibrated robot's episode lifts a copy of it."""
        self.randomize = randomizes(self.config, self.task, randomize)
        top = self.config.randomize.deadband[1]
        if self.randomize and top >= self.pipeline.max_speed:
            raise UsageError(
                f"max_speed {self.pipeline.max_speed:g} must lie above the dead-band it trains "
                f"with: [randomize] deadband reaches {top:g} (raise [actions] max_speed or "
                "lower the range)"
            )
        self.period = self.config.loop.period
        self.metadata = {**self.metadata, "render_fps": self.config.loop.rate_hz}
        width, height = (int(v) for v in image_size)
        self.observation_space = spaces.Box(0, 255, (height, width, 3), dtype=np.uint8)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self.world = JetbotWorld(self.config.sim, image_size=(width, height))
        self._frame = np.zeros(self.observation_space.shape, dtype=np.uint8)
        self._steps = 0
        self.scene: Scene = self.world.scene
        self.sim_params: dict[str, Any] = {}
        """The last reset's [sim] knobs (``randomize.DRAWN``), as in its ``info``."""

    @property
    def difficulty(self) -> float:
        return float(self.task.difficulty)

    @difficulty.setter
    def difficulty(self, value: float) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                not (math.isfinite(value) and 0.0 <= value <= 1.0):
            raise UsageError(f"difficulty must be a number in [0, 1], got {value!r}")
        if not self.task.curriculum and value != 1.0:
            raise UsageError(f"task {self.task.name!r} has no curriculum (its scene does not "
                             "read Task.difficulty): docs/CURRICULUM.md")
        if float(value) != self.difficulty:
            # load_task hands out one instance per name: this env's own copy, so that no
            # other env of the process (an evaluation's) sees the change
            self.task = copy.copy(self.task)
            self.task.difficulty = float(value)

    def _scene(self, options: dict[str, Any]) -> Scene:
        scene = self.task.scene(self.np_random, bool(options.get("start_noise",
                                                                 self.start_noise)))
        if "robot_pose" in options:
            x, y, yaw = (float(v) for v in options["robot_pose"])
            scene = dataclasses.replace(scene, robot_pose=(x, y, yaw))
        return scene

    def _info(self, duties: tuple[float, float]) -> dict[str, Any]:
        outcome = self.task.outcome(self.scene, self.world)
        if not isinstance(outcome, dict) or "is_success" not in outcome:
            raise UsageError(f"task {self.task.name!r}: outcome() must return a dict with "
                             f"'is_success', got {type(outcome).__name__}")
        return {
            **outcome,
            "pose": np.array(self.world.robot_pose()),
            "duty": np.array(duties),
            "sim_time": self.world.sim_time,
        }

    def _episode_sim(self) -> SimConfig:
        """This episode's [sim]: a draw from [randomize], or the config's (with a fresh noise
        seed when the camera is noisy); drawn after the scene, so randomization leaves the
        scenes of a seed as they are."""
        from jetbot_rt.sim.randomize import sample  # pybullet: only when an env is built

        sim = self.config.sim
        if self.randomize:
            return sample(sim, self.config.randomize, self.np_random)
        if sim.image_noise > 0:
            return dataclasses.replace(sim, seed=int(self.np_random.integers(2**31)))
        return sim

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        from jetbot_rt.sim.randomize import params as sim_params

        super().reset(seed=seed)
        self.scene = self._scene(options or {})
        self.world.reset(scene=self.scene, sim=self._episode_sim())
        self.sim_params = sim_params(self.world.sim)
        self.pipeline = self._unlifted
        error = self.config.randomize.deadband_lift
        if self.randomize and error is not None:
            lift = self.world.sim.deadband + float(self.np_random.uniform(*error))
            self.pipeline = dataclasses.replace(self.pipeline, deadband=min(max(lift, 0.0), 0.5))
            self.sim_params["deadband_lift"] = self.pipeline.deadband
        self._steps = 0
        self._frame = self.world.frame()
        return self._frame, {**self._info((0.0, 0.0)), "sim_params": self.sim_params}

    def step(
        self, action: np.ndarray
    ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        duties = self.pipeline.duties(np.asarray(action, dtype=np.float64).reshape(-1))
        self.world.set_duty(*duties)
        self.world.step(self.period)
        self._steps += 1
        self._frame = self.world.frame()
        info = self._info(duties)
        reward = float(self.task.reward(info))
        terminated = bool(self.task.terminated(info))
        truncated = not terminated and self._steps >= self.task.episode_steps
        return self._frame, reward, bool(terminated), truncated, info

    def render(self) -> np.ndarray | None:
        return self._frame.copy() if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        self.world.close()


def make_task_env(task: str | Task, config: Config | None = None, **kwargs: Any) -> JetbotEnv:
    """Picklable factory for vector envs (one PyBullet client per worker process)."""
    return JetbotEnv(task, config, **kwargs)
