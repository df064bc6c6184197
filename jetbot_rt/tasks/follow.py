"""``follow``: road following (NVIDIA jetbot's second camera task) on a closed track of tape.

Each episode draws a closed track around the room's centre (a radius that varies with the
angle: its curvature and size are random), the tape's width, and the tape's and the floor's
colours (always told apart: their luminance differs by at least ``min_contrast``). The robot
starts on the centre line, facing along it one way or the other. It must stay on the track --
its axle midpoint never farther than ``max_offset`` from the centre line -- for the whole
episode and cover at least ``min_progress`` along it. Leaving the track ends the episode
(failed); so a policy that drives straight on leaves at the first bend.

Draw order from the RNG (fixed; episodes replay from their seed): the track's size, its two
shape harmonics' amplitudes and phases, the stretch in x and y, the tape's width, the floor's
colour, the tape colour's candidates, the start angle and the direction of travel, then the
start noise (dx, dy, dyaw; always drawn, applied only with ``start_noise``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from jetbot_rt.tasks.api import Task, WorldView
from jetbot_rt.tasks.critic_state import (
    COMMAND_NAMES,
    DYNAMICS_NAMES,
    commands,
    dynamics,
    robot_frame,
)
from jetbot_rt.tasks.episode_state import EpisodeMemory
from jetbot_rt.tasks.scene import ROOM_HALF_SIZE, Scene, Tape

TRACK = "track"
TRACK_POINTS = 96
"""Points of the track's polyline (the tape's segments and the centre line alike)."""
WALL_MARGIN = 0.3
"""m; the centre line stays this far inside the room's walls."""
MIN_TURN_RADIUS = 0.35
"""m; the sharpest bend a track may have (the shape's amplitudes shrink until it holds)."""


@dataclass(frozen=True)
class Track:
    """A closed centre line: ``points`` (N, 2), ``s`` the arc length at each point (N + 1,
    the last the loop's length)."""

    points: np.ndarray
    s: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray) -> Track:
        ends = np.roll(points, -1, axis=0)
        lengths = np.linalg.norm(ends - points, axis=1)
        return cls(points, np.concatenate([[0.0], np.cumsum(lengths)]))

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def nearest(self, xy: np.ndarray) -> tuple[float, float]:
        """(distance to the centre line, arc length of the nearest point on it)."""
        a = self.points
        ab = np.roll(a, -1, axis=0) - a
        t = np.clip(np.einsum("ij,ij->i", xy - a, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
        closest = a + t[:, None] * ab
        gaps = np.linalg.norm(closest - xy, axis=1)
        i = int(np.argmin(gaps))
        return float(gaps[i]), float(self.s[i] + t[i] * (self.s[i + 1] - self.s[i]))

    def at(self, s: float) -> np.ndarray:
        """The centre line's point at arc length ``s`` (any real: the loop wraps)."""
        s = s % self.length
        i = min(int(np.searchsorted(self.s, s, side="right")) - 1, len(self.points) - 1)
        t = (s - self.s[i]) / max(self.s[i + 1] - self.s[i], 1e-12)
        return self.points[i] + t * (self.points[(i + 1) % len(self.points)] - self.points[i])


def track_of(scene: Scene, world: WorldView | None = None) -> Track:
    tape = scene.piece(TRACK)
    assert isinstance(tape, Tape)
    return Track.of(np.asarray(tape.points, dtype=np.float64))


def min_turn_radius(points: np.ndarray) -> float:
    """m; the smallest radius of the circle through three consecutive points."""
    a, b, c = np.roll(points, 1, axis=0), points, np.roll(points, -1, axis=0)
    ab, bc, ca = (np.linalg.norm(u - v, axis=1) for u, v in ((a, b), (b, c), (c, a)))
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    return float(np.min(ab * bc * ca / np.maximum(2 * cross, 1e-12)))


def luminance(rgb: tuple[float, float, float]) -> float:
    return 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]


class Follow(Task):
    name = "follow"
    description = "follow a closed track of tape (random shape, width, colours) without leaving it"
    episode_steps = 450
    """15 s at 30 Hz."""
    max_speed = 0.6
    """Duty at |mu| = 1: the randomized dead-band (up to 0.3) leaves half of it. At 0.5 the
    robots with the widest dead-bands crept (a trained student covered 0.9-1.4 m in 15 s)."""
    randomize = True
    max_offset = 0.12
    """m; the axle midpoint farther than this from the centre line: off the track (failed)."""
    min_progress = 1.5
    """m along the centre line (either way round) that success needs by the episode's end."""
    success_distance = None
    radius = (0.75, 1.05)
    """m; the track's mean radius, uniform."""
    harmonics = ((2, 0.22), (3, 0.12))
    """(k, largest amplitude): the radius varies by ``a_k cos(k angle + phase)``, a_k uniform
    in [0, largest]: an oval, a bean, a rounded triangle."""
    stretch = 0.15
    """The track is stretched in x and y by 1 +- this, each uniform."""
    width = (0.06, 0.15)
    """m; the tape's width, uniform."""
    min_contrast = 0.25
    """The luminance (0..1) the tape and the floor differ by at least."""
    start_xy_noise = 0.02
    start_yaw_noise = 0.15
    # DAgger with the pure-pursuit expert (docs/TRAINING.md, "follow").
    training = {"out": "runs/follow"}  # noqa: RUF012 - read only

    def __init__(self) -> None:
        self._memory = EpisodeMemory(track_of)

    def scene(self, rng: np.random.Generator, start_noise: bool) -> Scene:
        radius = rng.uniform(*self.radius)
        shape = [(k, rng.uniform(0, top), rng.uniform(0, 2 * math.pi))
                 for k, top in self.harmonics]
        sx, sy = 1 + rng.uniform(-self.stretch, self.stretch, 2)
        width = float(rng.uniform(*self.width))
        floor = tuple(float(c) for c in rng.uniform(0.1, 0.9, 3))
        candidates = rng.uniform(0.0, 1.0, (8, 3))
        start_angle = rng.uniform(0, 2 * math.pi)
        direction = 1 if rng.random() < 0.5 else -1
        noise = rng.uniform(-1, 1, 3)

        angles = np.linspace(0, 2 * math.pi, TRACK_POINTS, endpoint=False)
        scale = 1.0
        for _ in range(20):  # shrink the shape until the track is neither too sharp nor too big
            r = radius * (1 + scale * sum(a * np.cos(k * angles + ph) for k, a, ph in shape))
            points = np.stack([sx * r * np.cos(angles), sy * r * np.sin(angles)], axis=1)
            fit = (ROOM_HALF_SIZE - WALL_MARGIN) / float(np.max(np.abs(points)))
            if fit < 1:
                points = points * fit
            if min_turn_radius(points) >= MIN_TURN_RADIUS:
                break
            scale *= 0.8
        tape_rgb = next((tuple(float(c) for c in rgb) for rgb in candidates
                         if abs(luminance(tuple(rgb)) - luminance(floor)) >= self.min_contrast),
                        (0.05, 0.05, 0.05) if luminance(floor) > 0.5 else (0.95, 0.95, 0.95))

        track = Track.of(points)
        s0 = start_angle / (2 * math.pi) * track.length
        here, ahead = track.at(s0), track.at(s0 + direction * 0.05)
        x, y = float(here[0]), float(here[1])
        yaw = math.atan2(ahead[1] - here[1], ahead[0] - here[0])
        if start_noise:
            x += self.start_xy_noise * float(noise[0])
            y += self.start_xy_noise * float(noise[1])
            yaw += self.start_yaw_noise * float(noise[2])
        tape = Tape(tuple((float(px), float(py)) for px, py in points), width, tape_rgb,
                    closed=True, name=TRACK)
        return Scene((x, y, yaw), (tape,), floor_color=floor)

    def outcome(self, scene: Scene, world: WorldView) -> dict[str, Any]:
        episode = self._memory.episode(scene, world)
        track: Track = episode.derived
        x, y, yaw = world.robot_pose()
        episode.advance(x, y)
        offset, s = track.nearest(np.array([x, y]))
        if "s" not in episode.extra:  # the episode's first look: its start and its way round
            heading = track.at(s + 0.05) - track.at(s)
            way = 1.0 if math.cos(yaw - math.atan2(heading[1], heading[0])) >= 0 else -1.0
            episode.extra.update(s=s, progress=0.0, way=way)
        step = (s - episode.extra["s"] + track.length / 2) % track.length - track.length / 2
        episode.extra["s"] = s
        episode.extra["progress"] += episode.extra["way"] * step
        progress = float(episode.extra["progress"])
        if offset > self.max_offset:
            episode.failed = True
        target = track.at(s + episode.extra["way"] * FollowExpert.lookahead)
        return {"offset": offset, "progress": progress, "progress_step": float(
                    episode.extra["way"] * step),
                "failed": episode.failed, "target_xy": target,
                "is_success": bool(not episode.failed and progress >= self.min_progress)}

    def reward(self, info: dict[str, Any]) -> float:
        """Progress along the track (m x 10), less the offset's square; -5 on leaving it."""
        if info["failed"]:
            return -5.0
        return 10.0 * info["progress_step"] - (info["offset"] / self.max_offset) ** 2 * 0.1

    def terminated(self, info: dict[str, Any]) -> bool:
        return bool(info["failed"])

    def expert(self) -> FollowExpert:
        return FollowExpert()

    critic_state_names = ("target_ahead", "target_left", "offset", "progress",
                          *COMMAND_NAMES, *DYNAMICS_NAMES)

    def critic_state(self, info: dict[str, Any]) -> np.ndarray:
        """The pure-pursuit target (the centre line 0.15 m ahead) in the robot's frame (in
        lookaheads: where the track goes and which side of it the robot is on), the offset
        from the centre line (in ``max_offset``s), the progress along it (in
        ``min_progress``, clipped to +-2), the last wheel commands and the episode's
        dynamics (``critic_state.py``)."""
        ahead, left = robot_frame(info["pose"], info["target_xy"])
        lookahead = FollowExpert.lookahead
        progress = float(np.clip(float(info["progress"]) / self.min_progress, -2.0, 2.0))
        return np.array([ahead / lookahead, left / lookahead,
                         float(info["offset"]) / self.max_offset, progress,
                         *commands(info, self.max_speed), *dynamics(info)], dtype=np.float32)


@dataclass(frozen=True)
class FollowExpert:
    """Pure pursuit on the centre line: steer onto the arc through the point ``lookahead``
    ahead along the track (``info["target_xy"]``, which the task computes), at a constant
    forward command."""

    lookahead = 0.15
    """m along the centre line (a class constant: the task computes the target with it).
    Pure pursuit cuts a bend's inside by more the farther it looks: at 0.25 m the expert ran
    2.0 cm from the centre line, at 0.15 m 0.8 cm (the median of 100 randomized episodes'
    medians; ``benchmarks/bench_expert_choices.py``), of the 12 cm a student may stray
    before it has left the track."""
    min_forward: float = 0.75
    """The forward command: above the randomized dead-band's share (0.3 duty of 0.6). 0.75,
    not the 0.8 it was: DAgger's ``--min-forward`` default replaced it until 2026-12-07, so
    every follow student was trained at 0.75."""
    half_track: float = 0.055
    """m; half the distance between the wheels."""
    turn_gain: float = 1.0
    """Times the turn pure pursuit asks for."""

    reads: tuple[str, ...] = ("pose", "target_xy")

    def label(self, info: dict[str, Any]) -> np.ndarray:
        x, y, yaw = (float(v) for v in info["pose"])
        dx, dy = float(info["target_xy"][0]) - x, float(info["target_xy"][1]) - y
        ahead = math.cos(yaw) * dx + math.sin(yaw) * dy
        left = -math.sin(yaw) * dx + math.cos(yaw) * dy
        if ahead <= 0.02:  # the target beside or behind: turn toward it on the spot
            turn = math.copysign(1.0, left)
            return np.array([-turn * 0.8, turn * 0.8], dtype=np.float32)
        curvature = 2 * left / (ahead * ahead + left * left)
        forward = self.min_forward
        turn = float(np.clip(self.turn_gain * forward * curvature * self.half_track, -1, 1))
        return np.clip(np.array([forward - turn, forward + turn], dtype=np.float32), -1, 1)
