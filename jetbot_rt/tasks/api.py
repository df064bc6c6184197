"""The task API: one class says what a task's scene holds, how it is drawn, and what counts.

Subclass ``Task``, set its class attributes and write ``scene`` and ``outcome`` (``reward``,
``terminated`` and ``expert`` have defaults). docs/TASKS.md is the tutorial;
``examples/tasks/my_task.py`` a whole one. The simulator builds the scene and asks the task
about it; the trainer adds its shaping in wrappers around the env, never here, so the
evaluation is the task's alone. Observations are the camera image, actions the two wheel
commands: a task decides neither.
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol, Tuple

import numpy as np

from jetbot_rt.tasks.scene import Box, Scene


class WorldView(Protocol):
    """What a task may ask the simulated world (``jetbot_rt.sim.world.JetbotWorld``) in
    ``outcome``. Names are the pieces' ``name``s."""

    sim_time: float

    def robot_pose(self) -> tuple[float, float, float]:
        """x, y (m) and yaw (rad) of the robot's axle midpoint."""

    def robot_speed(self) -> float:
        """Horizontal speed (m/s)."""

    def position(self, name: str) -> tuple[float, float, float]:
        """A piece's centre now (m)."""

    def shift(self, name: str) -> float:
        """How far (m, on the floor) a piece moved since the scene was built."""

    def distance(self, name: str) -> float:
        """From the robot's axle midpoint to a piece's centre, in 3-D (m)."""

    def touching(self, name: str | None = None) -> bool:
        """Whether the robot touches the piece (None: any piece, the clutter or the room's
        walls)."""

    def clutter(self) -> tuple[Box, ...]:
        """The footprints of what the simulator put in the room beside the task's scene
        (``[sim] clutter``: furniture at the walls; a cylinder as the square around it). The
        robot collides with them; a task whose success is "touch nothing" must see them."""


class Expert(Protocol):
    """A privileged teacher for DAgger: reads the simulator's state from the env's ``info``
    (the keys in ``reads``), never the image. Must be picklable (it travels to env workers)."""

    reads: tuple[str, ...]

    def label(self, info: dict[str, Any]) -> np.ndarray:
        """``[left, right]`` in [-1, 1]: the teacher's action in the state ``info`` shows.

        Optional: ``symmetric(info) -> bool``, true where the teacher's rule is the same
        mirrored: in the scene seen in a mirror it would answer this label with its wheels
        swapped. DAgger's ``--mirror`` flips only those frames (``dagger.regress``)."""


class Task:
    """A task. Instances are made without arguments (``load_task`` does ``Class()``)."""

    name: ClassVar[str] = ""
    """Short name: run directories (``runs/<name>``), messages. Default: the class name."""
    description: ClassVar[str] = ""
    """One line for ``jetbot-train --help``."""
    episode_steps: ClassVar[int] = 450
    """Time limit in control ticks (the env's ``truncated``; 15 s at 30 Hz)."""
    max_speed: ClassVar[float] = 0.1
    """Duty at |mu| = 1 the task trains with (exported into the policy's metadata). With
    ``randomize`` it must lie above ``[randomize] deadband``'s top."""
    randomize: ClassVar[bool] = False
    """Domain randomization (``[randomize]`` ranges) unless the env or the config says."""
    success_distance: ClassVar[float | None] = None
    """m; for tasks whose success is "closer than this": the evaluation prints it beside the
    mean final ``distance`` (the key ``outcome`` reports)."""
    training: ClassVar[dict[str, Any]] = {}
    """The trainer's option defaults for this task (``jetbot-train train`` flags spelled as
    ``PPOArgs`` fields, ``model`` a dict); the command line and ``[train]`` override them."""
    curriculum: ClassVar[bool] = False
    """Whether ``scene`` reads ``difficulty`` (``jetbot-train train --curriculum`` refuses a
    task that does not say so: its scenes would not change)."""
    difficulty: float = 1.0
    """0 (the easiest scenes) .. 1 (the task as evaluated). The trainer's ``--curriculum``
    raises it as the student succeeds (docs/CURRICULUM.md); everything else -- evaluation,
    ``jetbot-rt run --backend sim``, a plain training -- leaves it at 1. Read it in ``scene``,
    e.g. through ``between``; at 1 the scenes must be the task's full ones."""

    def scene(self, rng: np.random.Generator, start_noise: bool) -> Scene:
        """One episode's scene, drawn from ``rng`` alone (episodes replay from their seed).
        ``start_noise`` False: the robot at its nominal pose; draw the same numbers either way,
        so that the pieces of a seed do not depend on it."""
        raise NotImplementedError

    def between(self, easy: tuple[Any, ...], full: tuple[Any, ...]) -> tuple[Any, ...]:
        """A range (or any tuple of numbers) at this ``difficulty``: ``easy`` at 0, ``full``
        at 1 (exactly: a seed's scene at difficulty 1 is the one it always was), each number
        linear in between; rounded to the nearest integer where both ends are integers."""
        if self.difficulty >= 1.0:
            return full
        d = max(0.0, float(self.difficulty))
        return tuple(round(e + d * (f - e)) if isinstance(e, int) and isinstance(f, int)
                     else e + d * (f - e) for e, f in zip(easy, full))

    def outcome(self, scene: Scene, world: WorldView) -> dict[str, Any]:
        """The success test on the world as it is now: a dict with ``is_success`` (bool) and
        the quantities it uses (numbers or arrays), which the env returns in ``info``."""
        raise NotImplementedError

    def reward(self, info: dict[str, Any]) -> float:
        """The env's reward for a step (``info``: ``outcome``'s keys plus ``pose``, ``duty``,
        ``sim_time``). Default: 1 on a successful step. Shaping is the trainer's business."""
        return 1.0 if info["is_success"] else 0.0

    def terminated(self, info: dict[str, Any]) -> bool:
        """Whether the episode ends now (``terminated``). Default: never (time limit only)."""
        return False

    def expert(self) -> Expert | None:
        """A privileged teacher for ``--algo dagger`` (the default algorithm when there is
        one), or None."""
        return None

    critic_state_names: ClassVar[tuple[str, ...]] = ()
    """What each value ``critic_state`` returns means, in order; its length is the width of
    the state an asymmetric critic reads. Empty (the default): the task has no privileged
    state, and ``jetbot-train train --critic state`` refuses it."""

    def critic_state(self, info: dict[str, Any]) -> np.ndarray | None:
        """The simulator's privileged state for an asymmetric critic (PPO's ``--critic
        state``, Pinto et al. 2018): a float vector of ``len(critic_state_names)`` values,
        each scaled to about unit size, computed from ``info`` -- ``outcome``'s keys plus
        ``pose``, ``duty``, ``sim_time`` and ``sim_params`` (this episode's ``[sim]`` knobs,
        randomized or not). Only the critic reads it, and only while training: the policy
        still sees the camera image alone, and nothing of it reaches the exported ONNX.
        Default: None (no privileged state)."""
        return None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if not cls.__dict__.get("name"):  # each class its own, never its base's
            cls.name = cls.__name__.lower()

    @classmethod
    def short_name(cls) -> str:
        return cls.name


Pose = Tuple[float, float, float]
