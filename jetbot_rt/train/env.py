"""The Gymnasium environment: the runtime's sim world, camera and action pipeline as an Env.

A step does what one tick of ``jetbot-rt run --backend sim`` does, in the same order: the
action goes through ``ActionPipeline`` (max_speed, clamp, trim, sign), the duties to
``JetbotWorld.set_duty``, the world advances one control period, and the camera frame
rendered after that step is the next observation. ``reset`` renders the first frame.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from jetbot_rt.actions import ActionPipeline
from jetbot_rt.config import Config, SimConfig
from jetbot_rt.errors import UsageError

POLICY_IMAGE_SIZE = 56
"""Side of the square camera image the trainer renders and its networks take (the one
source of the training size): docs/SIM.md, "The render-size seam", says why 56."""
MIN_REWARD_DISTANCE = 0.01
"""m; the reward's 1/d is evaluated at no less than this (bodies never get this close)."""


@dataclass(frozen=True)
class Task:
    name: str
    robot_pose: tuple[float, float, float]
    """Nominal start (x, y, yaw) of the robot's axle midpoint."""
    block_xy: tuple[float, float]
    episode_steps: int
    """Episodes end only by this time limit (control ticks)."""
    success_distance: float
    """m; an episode succeeds when the final robot-block distance is below this."""
    start_xy_noise: float
    """m; uniform +- noise on the start x and y (seeded by ``reset(seed=...)``)."""
    start_yaw_noise: float
    """rad; uniform +- noise on the start yaw."""
    randomize: bool = False
    """Domain randomization ([randomize] ranges) unless the env or the config says otherwise."""


TASKS: dict[str, Task] = {
    # Why these numbers: docs/TRAINING.md ("The forward task").
    "forward": Task(
        name="forward",
        robot_pose=(-0.6, 0.0, 0.0),
        block_xy=(0.3, 0.0),
        episode_steps=450,
        success_distance=0.15,
        start_xy_noise=0.02,
        start_yaw_noise=0.15,
    ),
}


def get_task(name: str) -> Task:
    if name not in TASKS:
        raise UsageError(f"unknown task {name!r} (known: {', '.join(sorted(TASKS))})")
    return TASKS[name]


def forward_reward(distance: float) -> float:
    """The seed task's reward, ``exp(1/d) - 30``."""
    return math.exp(1.0 / max(distance, MIN_REWARD_DISTANCE)) - 30.0


def action_pipeline_of(config: Config, model_max_speed: float | None = None) -> ActionPipeline:
    """The pipeline the runtime builds: max_speed from config, else the model's, else 0.1."""
    return ActionPipeline.from_config(config.actions, model_max_speed)


def max_speed_of(config: Config) -> float:
    return action_pipeline_of(config).max_speed


class JetbotEnv(gym.Env[np.ndarray, np.ndarray]):
    """Observation: the camera image, HxWx3 uint8 RGB (``image_size`` = (width, height),
    default ``POLICY_IMAGE_SIZE`` square; an evaluation passes its policy's input size).
    Action: ``[left, right]`` in [-1, 1].

    ``model_max_speed`` is the policy's metadata value, used (as by the runtime) when the
    config sets none. ``randomize``: draw the ``[sim]`` knobs from ``[randomize]`` at each
    reset (default: ``[randomize] enabled``, else the task's choice); the draw is in the reset's
    ``info["sim_params"]``. ``reset(options={"start_noise": False})`` starts exactly at the task's
    nominal pose,
    ``options={"robot_pose": (x, y, yaw)}`` at a given one.
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
    ) -> None:
        from jetbot_rt.sim.world import JetbotWorld  # pybullet: only when an env is built

        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise UsageError(f"unknown render_mode {render_mode!r} (known: rgb_array)")
        self.task = task if isinstance(task, Task) else get_task(task)
        self.config = config or Config()
        self.render_mode = render_mode
        self.start_noise = start_noise
        self.pipeline = action_pipeline_of(self.config, model_max_speed)
        if randomize is None:
            randomize = self.config.randomize.enabled
        self.randomize = self.task.randomize if randomize is None else randomize
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
        self.sim_params: dict[str, Any] = {}
        """The last reset's [sim] knobs (``randomize.DRAWN``), as in its ``info``."""

    def _start_pose(self, options: dict[str, Any]) -> tuple[float, float, float]:
        if "robot_pose" in options:
            x, y, yaw = (float(v) for v in options["robot_pose"])
            return (x, y, yaw)
        x, y, yaw = self.task.robot_pose
        if options.get("start_noise", self.start_noise):
            dx, dy = self.np_random.uniform(-self.task.start_xy_noise, self.task.start_xy_noise, 2)
            dyaw = self.np_random.uniform(-self.task.start_yaw_noise, self.task.start_yaw_noise)
            x, y, yaw = x + float(dx), y + float(dy), yaw + float(dyaw)
        return (x, y, yaw)

    def _aim_error(self) -> float:
        """m; how far the block's centre lies from the robot's line of travel (the distance
        to it when the block is beside or behind the robot). 0 when aimed straight at it."""
        x, y, yaw = self.world.robot_pose()
        bx, by, _ = self.world.block_position()
        dx, dy = bx - x, by - y
        bearing = math.atan2(dy, dx) - yaw
        bearing = abs(math.atan2(math.sin(bearing), math.cos(bearing)))
        return math.hypot(dx, dy) * math.sin(min(bearing, math.pi / 2))

    def _info(self, duties: tuple[float, float]) -> dict[str, Any]:
        distance = self.world.distance_to_block()
        return {
            "distance": distance,
            "aim_error": self._aim_error(),
            "is_success": distance < self.task.success_distance,
            "pose": np.array(self.world.robot_pose()),
            "duty": np.array(duties),
            "sim_time": self.world.sim_time,
        }

    def _episode_sim(self) -> SimConfig:
        """This episode's [sim]: a draw from [randomize], or the config's (with a fresh noise
        seed when the camera is noisy); drawn after the start pose, so randomization leaves
        the start poses of a seed as they are."""
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
        pose = self._start_pose(options or {})
        self.world.reset(robot_pose=pose, block_xy=self.task.block_xy, sim=self._episode_sim())
        self.sim_params = sim_params(self.world.sim)
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
        reward = forward_reward(info["distance"])
        truncated = self._steps >= self.task.episode_steps
        return self._frame, reward, False, truncated, info

    def render(self) -> np.ndarray | None:
        return self._frame.copy() if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        self.world.close()


def make_task_env(task: str, config: Config | None = None, **kwargs: Any) -> JetbotEnv:
    """Picklable factory for vector envs (one PyBullet client per worker process)."""
    return JetbotEnv(task, config, **kwargs)
