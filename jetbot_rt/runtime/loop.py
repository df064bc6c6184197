"""The fixed-rate control loop, ros2_control's cycle: read (the newest frame) -> update (policy,
actions) -> write (the drive), on absolute monotonic deadlines; then the robot's time passes
(``Robot.step``: the sim's world step, nothing on hardware), outside the tick's timing; then the
tick's result goes to its observers (telemetry, the recorder, the service notifier).

A tick that ends past its successor's deadline skips the missed ticks and counts them: the
loop never bursts to catch up, so a slow moment never turns into a rush of stale commands.

A frame's age is the camera's to say (``Camera.frame_age``): on hardware the wall time since
it arrived, on the sim the simulated time since it was rendered.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

import numpy as np

from jetbot_rt.errors import Fault
from jetbot_rt.hal.base import Frame, Robot
from jetbot_rt.runtime.actions import ActionPipeline
from jetbot_rt.runtime.histogram import Histogram
from jetbot_rt.runtime.safety import GuardedDrive, SafeStopLatch, Watchdog


class Policy(Protocol):
    def infer(self, image: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class TickResult:
    """What one completed tick saw and did, handed to every tick observer; it formats its own
    telemetry record (``record``), which the observers call off the control thread.

    ``image`` is the frame exactly as the policy received it (HxWx3 uint8 RGB, before the
    policy's own colour, dtype and layout conversion). Times are ``time.monotonic()`` seconds;
    durations are milliseconds.
    """

    tick: int
    t_start: float
    deadline: float
    image: np.ndarray
    frame_index: int
    frame_age_ms: float
    mu: list[float]
    cmd: tuple[float, float]
    infer_ms: float
    tick_ms: float
    write_ms: float
    advance_ms: float | None
    overruns: int
    extra: dict[str, Any]
    """The backend's per-tick fields (the sim's ``pose`` and ``sim_time``)."""

    @property
    def t_end(self) -> float:
        """When the timed part of the tick (read, update, write) ended."""
        return self.t_start + self.tick_ms / 1e3

    def record(self, t0: float) -> dict[str, Any]:
        """The telemetry record of this tick (``t`` relative to ``t0``)."""
        record: dict[str, Any] = {
            "t": round(self.t_start - t0, 6),
            "tick": self.tick,
            "state": "driving",
            "mu": self.mu,
            "cmd": list(self.cmd),
            "frame_age_ms": round(self.frame_age_ms, 3),
            "infer_ms": round(self.infer_ms, 3),
            "tick_ms": round(self.tick_ms, 3),
            "overruns": self.overruns,
            "late_ms": round((self.t_start - self.deadline) * 1e3, 3),
            "write_ms": round(self.write_ms, 3),
        }
        if self.advance_ms is not None:
            record["advance_ms"] = round(self.advance_ms, 3)
        record.update(self.extra)
        return record


class TickObserver(Protocol):
    """Called on the control thread after each completed tick: it must return at once (hand
    work to another thread) and never raise."""

    def __call__(self, result: TickResult, /) -> None: ...


@dataclass
class LoopStats:
    ticks: int = 0
    overruns: int = 0
    tick_ms: Histogram = field(default_factory=Histogram)
    infer_ms: Histogram = field(default_factory=Histogram)
    t_start: float | None = None
    t_end: float | None = None

    @property
    def elapsed(self) -> float:
        if self.t_start is None or self.t_end is None:
            return 0.0
        return self.t_end - self.t_start

    @property
    def achieved_hz(self) -> float:
        return self.ticks / self.elapsed if self.elapsed > 0 else 0.0


@dataclass(frozen=True)
class Schedule:
    """When ticks run and which frames they accept."""

    period: float
    max_frame_age: float
    clock: Callable[[], float] = time.monotonic


@dataclass(frozen=True)
class StopChain:
    """The safe-stop chain a tick answers to: the latch, the drive it guards, the watchdog."""

    latch: SafeStopLatch
    drive: GuardedDrive
    watchdog: Watchdog | None = None


class _Written(NamedTuple):
    """What the read -> update -> write part of a tick did, with its clock readings."""

    frame: Frame
    frame_age: float
    mu: list[float]
    cmd: tuple[float, float]
    t_infer: float
    t_act: float
    t_written: float


class ControlLoop:
    def __init__(
        self,
        *,
        robot: Robot,
        policy: Policy,
        actions: ActionPipeline,
        safety: StopChain,
        schedule: Schedule,
        observers: Sequence[TickObserver] = (),
        stats: LoopStats | None = None,
    ) -> None:
        self.robot = robot
        self.policy = policy
        self.actions = actions
        self.safety = safety
        self.latch = safety.latch
        self.schedule = schedule
        self.period = schedule.period
        self.clock = schedule.clock
        self.observers = list(observers)
        self.stats = stats if stats is not None else LoopStats()

    def run(self, duration: float | None = None) -> None:
        """Tick until the latch trips (fault, signal, stop command) or ``duration`` ends."""
        stats = self.stats
        stats.t_start = deadline = self.clock()
        end = stats.t_start + duration if duration is not None else None
        try:
            while not self.latch.tripped:
                now = self.clock()
                if end is not None and now >= end:
                    self.latch.trip(f"duration {duration:g} s reached", fault=False)
                    break
                try:
                    self._tick(deadline, now)
                except Fault as fault:
                    if not (fault.STOP_REQUEST_GRACE_S
                            and self.latch.wait(fault.STOP_REQUEST_GRACE_S)):
                        self.latch.trip(str(fault))
                    break
                except Exception as exc:  # any bug inside a tick ends in the safe stop
                    self.latch.trip(f"exception in tick: {type(exc).__name__}: {exc}")
                    break
                deadline += self.period
                tick_start, now = now, self.clock()
                if now > deadline:
                    missed = int((now - deadline) // self.period) + 1
                    stats.overruns += missed
                    deadline += missed * self.period
                if deadline - tick_start < self.period / 2:
                    # This tick began over half a period late (a slow wake-up under load):
                    # skip the next deadline too rather than tick again a moment later.
                    stats.overruns += 1
                    deadline += self.period
                self.latch.wait(max(0.0, deadline - self.clock()))
        finally:
            stats.t_end = self.clock()

    def _tick(self, deadline: float, t_start: float) -> None:
        """One cycle: read, update, write (timed: ``tick_ms``); the robot's time step (timed
        apart: ``advance_ms``); the result to the observers."""
        written = self._read_update_write(t_start)
        if written is None:
            return  # the latch tripped meanwhile; the loop ends at its next check
        stats = self.stats
        stats.ticks += 1
        tick_ms = (written.t_written - t_start) * 1e3
        infer_ms = (written.t_act - written.t_infer) * 1e3
        stats.tick_ms.add(tick_ms)
        stats.infer_ms.add(infer_ms)
        if self.safety.watchdog is not None:
            self.safety.watchdog.kick()
        advance_ms = None
        if self.robot.simulated:
            self.robot.step(self.period)
            advance_ms = (self.clock() - written.t_written) * 1e3
        if not self.observers:
            return
        result = TickResult(
            tick=stats.ticks,
            t_start=t_start,
            deadline=deadline,
            image=written.frame.image,
            frame_index=written.frame.index,
            frame_age_ms=written.frame_age * 1e3,
            mu=written.mu,
            cmd=written.cmd,
            infer_ms=infer_ms,
            tick_ms=tick_ms,
            write_ms=(written.t_written - written.t_act) * 1e3,
            advance_ms=advance_ms,
            overruns=stats.overruns,
            extra=self.robot.state(),
        )
        for observer in self.observers:
            observer(result)

    def _read_update_write(self, t_start: float) -> _Written | None:
        frame = self.robot.camera.read()
        if frame is None:
            raise Fault("camera delivered no frame")
        frame_age = self.robot.camera.frame_age(frame, t_start)
        max_age = self.schedule.max_frame_age
        if frame_age > max_age:
            raise Fault(
                f"stale frame: {frame_age * 1e3:.0f} ms old (limit [loop] max_frame_age = "
                f"{max_age:.3g} s)"
            )
        t_infer = self.clock()
        mu = self.policy.infer(frame.image)
        t_act = self.clock()
        cmd = self.actions.duties(mu)
        if not self.safety.drive.write(*cmd):
            return None
        return _Written(frame, frame_age, [float(mu[0]), float(mu[1])], cmd, t_infer, t_act,
                        self.clock())
