"""The simulated JetBot in its room: one PyBullet client per world, a modelled motor board,
and the robot's camera rendered with PyBullet's software renderer (headless, deterministic).

The real robot's imperfections (``[sim]`` keys, ideal by default) live in their own modules:
the motors in ``motor.py``, the camera's mount, latency and sensor in ``camera_model.py``, the
scene's colours and light in ``appearance.py``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from collections.abc import Sequence
from importlib import resources
from typing import TYPE_CHECKING

import cv2
import numpy as np

from jetbot_rt.errors import UsageError
from jetbot_rt.hal.base import DEFAULT_FRAME_SIZE, finite_pair
from jetbot_rt.sim import appearance, looks
from jetbot_rt.sim.camera_look import CameraLook
from jetbot_rt.sim.camera_model import CAMERA_ASPECT, FrameQueue, SensorEffects, mount_delta
from jetbot_rt.sim.lens import lens_warp
from jetbot_rt.sim.motor import WheelMotors
from jetbot_rt.sim.native_output import pybullet_chatter_filtered
from jetbot_rt.sim.pybullet_import import import_pybullet
from jetbot_rt.tasks.scene import BLOCK_HALF_SIZE, Block, Box, Piece, Scene, Tape, Wall, rgb

p = import_pybullet()

if TYPE_CHECKING:
    from jetbot_rt.sim.config import SimConfig

ASSETS = resources.files("jetbot_rt.sim") / "assets"

WHEEL_RADIUS = 0.03
"""m; also the spawn height of base_link (the axle midpoint)."""
CAMERA_NEAR = 0.01
CAMERA_FAR = 5.0
"""m; the room's diagonal is 4.2 m."""
GRAVITY = -9.81
TAPE_HALF_THICKNESS = 0.0005
"""m; tape lies this much above the floor's top (z = 0), which it would flicker through."""

LEFT, RIGHT, CAMERA_LINK = 0, 1, 3  # joint/link indices in jetbot.urdf's order
_WHEELS = (LEFT, RIGHT)


def pixel_centred(projection: tuple[float, ...], size: tuple[int, int]) -> list[float]:
    """Move a projection's image half a pixel left and down, so that each pixel shows
    what lies at its centre. As PyBullet's projection stands, TinyRenderer samples a pixel
    at its corner: its image sits half a pixel right of and above an area-averaged
    high-resolution view of the same scene, which at 64x64 adds half again to the mean
    pixel difference between them (docs/SIM.md, "The render-size seam").

    ``projection`` is column-major. x_ndc = x_clip / w_clip with w_clip = -z_view (row 3 is
    (0, 0, -1, 0)), so adding ``s`` to element 8 (row 0, column 2) moves x_ndc by ``-s``;
    a pixel is 2 / width in NDC. Likewise element 9 for y (image rows run down).
    """
    width, height = size
    shifted = list(projection)
    shifted[8] += 1.0 / width
    shifted[9] += 1.0 / height
    return shifted


def _asset(name: str) -> str:
    return str(ASSETS / name)


class JetbotWorld:
    """A JetBot in its room with a task's scene pieces, in one PyBullet client of its own.

    Several worlds can live in one process (each has its own client; the global default
    client is never used). ``image_size`` is (width, height) of ``render()``'s image;
    ``[sim] supersample`` renders it that many times larger and area-averages it down.
    """

    def __init__(
        self,
        sim: SimConfig,
        *,
        gui: bool = False,
        image_size: tuple[int, int] = DEFAULT_FRAME_SIZE,
    ) -> None:
        self._sim = sim
        self._dt_physics = 1.0 / sim.physics_hz
        self._width, self._height = (int(v) for v in image_size)
        if self._width < 1 or self._height < 1:
            raise UsageError(f"image size must be positive, got {image_size}")
        self._render_size = (self._width * sim.supersample, self._height * sim.supersample)
        if gui and sys.platform.startswith("linux") and not (
            os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
        ):
            raise UsageError("--gui needs a display (DISPLAY is not set); without one, run "
                             "the command under a virtual display: xvfb-run -a jetbot-rt ...")
        # the GUI's start-up chatter comes from its threads until the scene is built
        with pybullet_chatter_filtered():
            self._client = p.connect(p.GUI if gui else p.DIRECT)
            if self._client < 0:
                raise UsageError("cannot open a PyBullet " + ("window" if gui else "client"))
            self._gui = gui
            if gui:
                # The side panel shows the robot's camera (each render's RGB), nothing else.
                for flag, on in ((p.COV_ENABLE_GUI, 1), (p.COV_ENABLE_RGB_BUFFER_PREVIEW, 1),
                                 (p.COV_ENABLE_DEPTH_BUFFER_PREVIEW, 0),
                                 (p.COV_ENABLE_SEGMENTATION_MARK_PREVIEW, 0)):
                    p.configureDebugVisualizer(flag, on, physicsClientId=self._client)
                p.resetDebugVisualizerCamera(
                    1.6, 0.0, -45.0, (-0.2, 0.0, 0.0), physicsClientId=self._client
                )
            self._duty = (0.0, 0.0)
            self._steps = 0
            self._requested_time = 0.0
            self.reset()

    def reset(
        self,
        robot_pose: tuple[float, float, float] = (-0.6, 0.0, 0.0),
        block_xy: tuple[float, float] = (0.3, 0.0),
        sim: SimConfig | None = None,
        distractors: Sequence[tuple[float, float, str]] = (),
        *,
        scene: Scene | None = None,
    ) -> None:
        """Build ``scene`` (a task's: the robot's pose and the pieces, in their order); without
        one, the robot at ``robot_pose`` (x, y, yaw), the goal block (``[sim] block_color``,
        named ``"goal"``) at ``block_xy`` and the ``distractors`` (``(x, y, colour name)``).
        Motors at rest, ``sim_time`` = 0. ``sim``: new ``[sim]`` settings from this episode on
        (the domain randomization's draw); the physics rate, the image size and supersample
        stay the world's own.

        The scene is rebuilt from its URDFs (a few ms): PyBullet keeps contact and
        overlapping-pair caches that moving the bodies back does not clear, and only a
        rebuilt world replays bit for bit like a new one.
        """
        if scene is None:
            scene = Scene(robot_pose, (Block(block_xy, name="goal"),
                                       *(Block((x, y), color) for x, y, color in distractors)))
        if sim is not None:
            self._sim = dataclasses.replace(
                sim, physics_hz=self._sim.physics_hz, supersample=self._sim.supersample
            )
        room_sim = self._sim
        if scene.floor_color is not None:
            room_sim = dataclasses.replace(room_sim, floor_color=list(rgb(scene.floor_color)))
        if scene.wall_color is not None:
            room_sim = dataclasses.replace(room_sim, wall_color=list(rgb(scene.wall_color)))
        c = self._client
        if self._gui:  # no half-built scene on screen
            p.configureDebugVisualizer(p.COV_ENABLE_RENDERING, 0, physicsClientId=c)
        p.resetSimulation(physicsClientId=c)
        p.setGravity(0, 0, GRAVITY, physicsClientId=c)
        p.setTimeStep(self._dt_physics, physicsClientId=c)
        p.setPhysicsEngineParameter(deterministicOverlappingPairs=1, physicsClientId=c)
        self._room = p.loadURDF(_asset(looks.room_urdf(room_sim)), useFixedBase=True,
                                physicsClientId=c)
        x, y, yaw = scene.robot_pose
        self._robot = p.loadURDF(
            _asset("jetbot.urdf"), (x, y, WHEEL_RADIUS), p.getQuaternionFromEuler((0, 0, yaw)),
            physicsClientId=c,
        )
        if not looks.textured(room_sim):
            appearance.apply_colors(c, self._room, None, room_sim)
        self._pieces: dict[str, int] = {}
        self._starts: dict[str, tuple[float, float]] = {}
        self._bodies: list[int] = []
        for piece in scene.pieces:
            body = self._build(piece)
            self._bodies.append(body)
            if piece.name:
                self._pieces[piece.name] = body
                self._starts[piece.name] = self._start_xy(piece, body)
        self._scene = scene
        self._clutter = looks.clutter_of(scene, room_sim)
        self._bodies.extend(looks.dress(c, self._room, scene, room_sim, self._clutter))
        info = p.getDynamicsInfo(self._robot, -1, physicsClientId=c)
        self._com_to_link = p.invertTransform(info[3], info[4], physicsClientId=c)
        # Free-wheeling until the first step: PyBullet's default joint motor would brake.
        p.setJointMotorControlArray(
            self._robot, _WHEELS, p.VELOCITY_CONTROL, forces=(0.0, 0.0), physicsClientId=c
        )
        if self._gui:
            p.configureDebugVisualizer(p.COV_ENABLE_RENDERING, 1, physicsClientId=c)
        self._duty = (0.0, 0.0)
        self._steps = 0
        self._requested_time = 0.0
        self._motors = WheelMotors(self._sim)
        self._effects = SensorEffects(self._sim)
        self._camera_look = CameraLook(self._sim, (self._width, self._height))
        self._frames = FrameQueue(round(self._sim.camera_latency * self._sim.physics_hz))
        self._delivered: tuple[int, np.ndarray] | None = None
        # a fisheye renders a wider pinhole and warps it to the frame (sim/lens.py)
        self._lens = lens_warp(self._sim, self._render_size)
        vfov, aspect, size = ((self._lens.vfov_deg, self._lens.aspect, self._lens.render_size)
                              if self._lens else
                              (self._sim.camera_vfov_deg, CAMERA_ASPECT, self._render_size))
        self._projection = pixel_centred(p.computeProjectionMatrixFOV(
            vfov, aspect, CAMERA_NEAR, CAMERA_FAR, physicsClientId=c), size)
        self._light = appearance.light_kwargs(self._sim)
        self._mount = mount_delta(self._sim)
        if self._frames.delay:
            self._frames.put(0, self.render())

    def _build(self, piece: Piece) -> int:
        """One piece's body, in the client (colours via ``scene.rgb``)."""
        c = self._client
        if isinstance(piece, Block):
            body = p.loadURDF(_asset("block.urdf"), (piece.xy[0], piece.xy[1], BLOCK_HALF_SIZE),
                              physicsClientId=c)
            color = rgb(piece.color) if piece.color is not None else (
                tuple(self._sim.block_color)
                if tuple(self._sim.block_color) != appearance.BLOCK_COLOR else None)
            if color is not None:  # a set colour passes through float32: only when it differs
                p.changeVisualShape(body, -1, rgbaColor=(*color, 1.0), physicsClientId=c)
            return body
        if isinstance(piece, Wall):
            piece = piece.as_box()
        if isinstance(piece, Box):
            half = [s / 2 for s in piece.size]
            shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=c)
            look = p.createVisualShape(p.GEOM_BOX, halfExtents=half,
                                       rgbaColor=(*rgb(piece.color), 1.0), physicsClientId=c)
            return p.createMultiBody(0.0, shape, look, (piece.xy[0], piece.xy[1], half[2]),
                                     p.getQuaternionFromEuler((0, 0, piece.yaw)),
                                     physicsClientId=c)
        if isinstance(piece, Tape):
            return self._tape(piece)
        raise UsageError(f"not a scene piece: {piece!r}")

    def _start_xy(self, piece: Piece, body: int) -> tuple[float, float]:
        if isinstance(piece, (Block, Box)):
            return (float(piece.xy[0]), float(piece.xy[1]))
        position, _ = p.getBasePositionAndOrientation(body, physicsClientId=self._client)
        return (float(position[0]), float(position[1]))

    def _tape(self, tape: Tape) -> int:
        """Tape: a flat visual box per segment (as long as the segment plus the width, so the
        corners close), no collision; one multibody holding them all."""
        c = self._client
        color = (*rgb(tape.color), 1.0)
        shapes, positions, orientations = [], [], []
        for (x0, y0), (x1, y1) in tape.segments():
            length = math.hypot(x1 - x0, y1 - y0) + tape.width
            shapes.append(p.createVisualShape(
                p.GEOM_BOX, halfExtents=(length / 2, tape.width / 2, TAPE_HALF_THICKNESS),
                rgbaColor=color, physicsClientId=c))
            positions.append(((x0 + x1) / 2, (y0 + y1) / 2, TAPE_HALF_THICKNESS))
            orientations.append(p.getQuaternionFromEuler((0, 0, math.atan2(y1 - y0, x1 - x0))))
        if not shapes:
            raise UsageError("tape needs at least two points")
        n = len(shapes)
        return p.createMultiBody(
            0.0, -1, -1, (0.0, 0.0, TAPE_HALF_THICKNESS),
            linkMasses=[0.0] * n, linkCollisionShapeIndices=[-1] * n,
            linkVisualShapeIndices=shapes, linkPositions=positions,
            linkOrientations=orientations, linkInertialFramePositions=[(0, 0, 0)] * n,
            linkInertialFrameOrientations=[(0, 0, 0, 1)] * n, linkParentIndices=[0] * n,
            linkJointTypes=[p.JOINT_FIXED] * n, linkJointAxis=[(0, 0, 1)] * n,
            physicsClientId=c)

    def set_duty(self, left: float, right: float) -> None:
        """Duties in [-1, 1] as the motor board gets them (clipped like a PWM output);
        the motors act on them from the next ``step`` (after ``[sim] latency``)."""
        left, right = finite_pair(left, right)  # NonFinite: a ValueError and a Fault
        self._duty = (min(max(left, -1.0), 1.0), min(max(right, -1.0), 1.0))
        self._motors.command(self._steps, *self._duty)

    def step(self, dt: float) -> None:
        """Advance by ``dt`` seconds in fixed physics sub-steps of 1/physics_hz.

        Time is counted in whole sub-steps: a ``dt`` that is not a multiple of the sub-step
        runs the nearest whole number of them, and the remainder carries to the next call.
        """
        if not (dt >= 0 and math.isfinite(dt)):
            raise ValueError(f"step dt must be a finite number >= 0, got {dt}")
        self._requested_time += dt
        n = round(self._requested_time * self._sim.physics_hz) - self._steps
        if n <= 0:
            return
        c = self._client
        captures = self._frames.captures(self._steps, self._steps + n)
        for _ in range(n):
            measured = self.wheel_velocities() if self._motors.needs_wheel_speed else None
            targets, forces = self._motors.substep(self._steps, measured)
            p.setJointMotorControlArray(
                self._robot, _WHEELS, p.VELOCITY_CONTROL,
                targetVelocities=targets, forces=forces, physicsClientId=c,
            )
            p.stepSimulation(physicsClientId=c)
            self._steps += 1
            if captures and captures[0] == self._steps:
                self._frames.put(captures.pop(0), self.render())

    def render(self) -> np.ndarray:
        """The robot camera's view of the world as it is now, before the camera's latency and
        sensor effects (``frame()`` applies them): (height, width, 3) uint8 RGB."""
        c = self._client
        eye, rotation = self.camera_pose()
        view = p.computeViewMatrix(
            eye.tolist(), (eye + rotation[:, 0]).tolist(), rotation[:, 2].tolist(),
            physicsClientId=c,
        )
        width, height = self._lens.render_size if self._lens else self._render_size
        _, _, rgba, _, _ = p.getCameraImage(
            width, height, view, self._projection,
            renderer=p.ER_TINY_RENDERER, flags=p.ER_NO_SEGMENTATION_MASK,
            physicsClientId=c, **self._light,
        )
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3]
        if self._lens:
            rgb = self._lens.warp(rgb)
        if self._sim.supersample > 1:
            return cv2.resize(rgb, (self._width, self._height), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(rgb)

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera's optical centre in the world and its axes as columns (x forward, y
        left, z up), the mount as configured."""
        state = p.getLinkState(self._robot, CAMERA_LINK, computeForwardKinematics=True,
                               physicsClientId=self._client)
        eye = np.array(state[4])
        rotation = np.array(p.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        if self._mount is not None:  # the mount as configured, relative to the URDF's
            eye = eye + rotation @ self._mount[0]
            rotation = rotation @ self._mount[1]
        return eye, rotation

    def frame(self) -> np.ndarray:
        """The frame the camera delivers now: the world ``[sim] camera_latency`` ago, with the
        sensor's blur, contrast, brightness and noise. At the ideal defaults, ``render()``.
        Asked twice at the same ``sim_time``, the same frame."""
        if self._delivered is not None and self._delivered[0] == self._steps:
            return self._delivered[1]
        raw = self._frames.frame_at(self._steps) if self._frames.delay else None
        image = raw if raw is not None else self.render()
        if not self._camera_look.ideal:  # exposure, white balance, vignetting, motion blur
            image = self._camera_look.apply(image, *looks.motion(self._client, self._robot))
        image = self._effects.apply(image)
        self._delivered = (self._steps, image)
        return image

    def _robot_frame(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """base_link's frame in the world. PyBullet reports a base's centre of mass, which
        jetbot.urdf puts 2 cm behind the axle; this undoes that offset."""
        c = self._client
        com_pos, com_orn = p.getBasePositionAndOrientation(self._robot, physicsClientId=c)
        return p.multiplyTransforms(com_pos, com_orn, *self._com_to_link, physicsClientId=c)

    @property
    def client(self) -> int:
        """The PyBullet client id: for scene pieces added from outside (the calibration's
        marker)."""
        return self._client

    def robot_pose(self) -> tuple[float, float, float]:
        """x, y (m) and yaw (rad) of base_link, the axle midpoint."""
        (x, y, _), (qx, qy, qz, qw) = self._robot_frame()
        yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        return (x, y, yaw)

    def robot_speed(self) -> float:
        """Horizontal speed (m/s) of the robot's centre of mass."""
        (vx, vy, _), _ = p.getBaseVelocity(self._robot, physicsClientId=self._client)
        return math.hypot(vx, vy)

    def _body(self, name: str) -> int:
        if name not in self._pieces:
            raise KeyError(f"no piece named {name!r} in this scene "
                           f"(named: {', '.join(sorted(self._pieces)) or 'none'})")
        return self._pieces[name]

    def position(self, name: str) -> tuple[float, float, float]:
        """The centre (m) of the piece called ``name``."""
        position, _ = p.getBasePositionAndOrientation(self._body(name),
                                                      physicsClientId=self._client)
        return tuple(position)

    def shift(self, name: str) -> float:
        """How far (m, on the floor) the piece called ``name`` moved since ``reset``."""
        x, y, _ = self.position(name)
        x0, y0 = self._starts[name]
        return math.hypot(x - x0, y - y0)

    def distance(self, name: str) -> float:
        """From the robot's base_link origin to the centre of the piece ``name``, 3-D (m)."""
        return math.dist(self._robot_frame()[0], self.position(name))

    def touching(self, name: str | None = None) -> bool:
        """Whether the robot touches the piece ``name`` (None: any piece, or a wall)."""
        c = self._client
        if name is not None:
            return bool(p.getContactPoints(self._robot, self._body(name), physicsClientId=c))
        if any(p.getContactPoints(self._robot, body, physicsClientId=c)
               for body in self._bodies):
            return True
        # The room is one body: its floor carries the wheels (normals vertical), its walls not.
        return any(abs(point[7][2]) < 0.5
                   for point in p.getContactPoints(self._robot, self._room, physicsClientId=c))

    def clutter(self) -> tuple[Box, ...]:
        """The footprints of the pieces ``reset`` added that are no part of the task's scene
        (``[sim] clutter``; a cylinder as the square around it)."""
        return tuple(piece.footprint() for piece in self._clutter)

    def has_piece(self, name: str) -> bool:
        return name in self._pieces

    @property
    def scene(self) -> Scene:
        """The scene ``reset`` built."""
        return self._scene

    def distance_to_block(self) -> float:
        """``distance("goal")``: the default scene's goal block."""
        return self.distance("goal")

    def block_position(self) -> tuple[float, float, float]:
        """``position("goal")``."""
        return self.position("goal")

    def block_shift(self) -> float:
        """``shift("goal")``."""
        return self.shift("goal")

    def wheel_velocities(self) -> tuple[float, float]:
        """Measured (left, right) wheel angular velocities, rad/s, positive forward."""
        states = p.getJointStates(self._robot, _WHEELS, physicsClientId=self._client)
        return (states[0][1], states[1][1])

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) of ``render()``'s image."""
        return (self._width, self._height)

    @property
    def duty(self) -> tuple[float, float]:
        """The duties last written (the motors act on them after ``[sim] latency``)."""
        return self._duty

    @property
    def sim(self) -> SimConfig:
        """The ``[sim]`` settings of the current episode."""
        return self._sim

    @property
    def sim_time(self) -> float:
        """Simulated seconds since the last reset (whole physics sub-steps)."""
        return self._steps / self._sim.physics_hz

    def close(self) -> None:
        """Disconnect the PyBullet client. Idempotent."""
        if self._client >= 0:
            with pybullet_chatter_filtered():
                p.disconnect(physicsClientId=self._client)
            self._client = -1

    def __enter__(self) -> JetbotWorld:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
