"""The fixed-rate control loop: read -> infer -> act -> write, on absolute monotonic deadlines.

A tick that ends past its successor's deadline skips the missed ticks and counts them: the
loop never bursts to catch up, so a slow moment never turns into a rush of stale commands.
"""

from __future__ import annotations

import time
from collections.abc import Callable
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
        if not self.telemetry.enabled:
            return
        record: dict[str, Any] = {
            "t": round(t_start - self.telemetry.t0, 6),
            "tick": stats.ticks,
            "state": "driving",
            "mu": self.last_mu,
            "cmd": [left, right],
            "frame_age_ms": round(frame_age * 1e3, 3),
            "infer_ms": round(infer_ms, 3),
            "tick_ms": round(tick_ms, 3),
            "overruns": stats.overruns,
            "late_ms": round((t_start - deadline) * 1e3, 3),
            "write_ms": round((t_written - t_act) * 1e3, 3),
        }
        if self.advance is not None:
            record["advance_ms"] = round((t_end - t_written) * 1e3, 3)
        if self.extra_telemetry is not None:
            record.update(self.extra_telemetry())
        self.telemetry.record(record)
