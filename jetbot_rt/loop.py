"""The fixed-rate control loop: read -> infer -> act -> write, on absolute monotonic deadlines.

A tick that ends past its successor's deadline skips the missed ticks and counts them: the
loop never bursts to catch up, so a slow moment never turns into a rush of stale commands.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from jetbot_rt.actions import ActionPipeline
from jetbot_rt.errors import Fault
from jetbot_rt.hal.base import Camera
from jetbot_rt.histogram import Histogram
from jetbot_rt.safety import GuardedDrive, SafeStopLatch, Watchdog
from jetbot_rt.telemetry import Telemetry


class Policy(Protocol):
    def infer(self, image: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class TickResult:
    """What one completed tick saw and did, handed to every tick observer.

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


TickObserver = "Callable[[TickResult], None]"
"""A type alias kept a string: ``collections.abc.Callable[...]`` raises at run time on the
robot's Python 3.8."""
"""Called on the control thread after each completed tick: it must return at once (hand work
to another thread) and never raise."""


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


class ControlLoop:
    def __init__(
        self,
        *,
        camera: Camera,
        policy: Policy,
        actions: ActionPipeline,
        drive: GuardedDrive,
        latch: SafeStopLatch,
        watchdog: Watchdog | None,
        telemetry: Telemetry,
        period: float,
        max_frame_age: float,
        advance: Callable[[float], None] | None = None,
        extra_telemetry: Callable[[], dict[str, Any]] | None = None,
        on_tick_done: Callable[[float], None] | None = None,
        observers: Sequence[TickObserver] = (),
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.camera = camera
        self.policy = policy
        self.actions = actions
        self.drive = drive
        self.latch = latch
        self.watchdog = watchdog
        self.telemetry = telemetry
        self.period = period
        self.max_frame_age = max_frame_age
        self.advance = advance
        self.extra_telemetry = extra_telemetry
        self.on_tick_done = on_tick_done
        self.observers = list(observers)
        self.clock = clock
        self.stats = LoopStats()
        self.last_mu: list[float] = [0.0, 0.0]

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
        stats = self.stats
        frame = self.camera.read()
        if frame is None:
            raise Fault("camera delivered no frame")
        frame_age = t_start - frame.t_capture
        if frame_age > self.max_frame_age:
            raise Fault(
                f"stale frame: {frame_age * 1e3:.0f} ms old (max_frame_age "
                f"{self.max_frame_age * 1e3:.0f} ms)"
            )
        t_infer = self.clock()
        mu = self.policy.infer(frame.image)
        t_act = self.clock()
        left, right = self.actions.duties(mu)
        self.last_mu = [float(mu[0]), float(mu[1])]
        if not self.drive.write(left, right):
            return  # the latch tripped meanwhile; the loop ends at its next check
        t_written = self.clock()
        if self.advance is not None:
            self.advance(self.period)
        t_end = self.clock()

        stats.ticks += 1
        tick_ms = (t_end - t_start) * 1e3
        infer_ms = (t_act - t_infer) * 1e3
        stats.tick_ms.add(tick_ms)
        stats.infer_ms.add(infer_ms)
        if self.watchdog is not None:
            self.watchdog.kick()
        if self.on_tick_done is not None:
            self.on_tick_done(t_end)
        if not (self.telemetry.enabled or self.observers):
            return
        result = TickResult(
            tick=stats.ticks,
            t_start=t_start,
            deadline=deadline,
            image=frame.image,
            frame_index=frame.index,
            frame_age_ms=frame_age * 1e3,
            mu=self.last_mu,
            cmd=(left, right),
            infer_ms=infer_ms,
            tick_ms=tick_ms,
            write_ms=(t_written - t_act) * 1e3,
            advance_ms=(t_end - t_written) * 1e3 if self.advance is not None else None,
            overruns=stats.overruns,
            extra=self.extra_telemetry() if self.extra_telemetry is not None else {},
        )
        for observer in self.observers:
            observer(result)
        if self.telemetry.enabled:
            self.telemetry.record(result.record(self.telemetry.t0))
