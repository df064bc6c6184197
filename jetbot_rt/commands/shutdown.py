"""The stop phase of ``jetbot-rt run``: ``Shutdown`` releases what start-up brought up, in a
fixed order that leaves the motors at zero last, and reports the run as a ``Summary``."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from jetbot_rt.errors import EXIT_OK, EXIT_SAFE_STOP, EXIT_USAGE
from jetbot_rt.recording.recorder import recording_line

if TYPE_CHECKING:
    from jetbot_rt.commands.lifecycle import Lifecycle
    from jetbot_rt.hal.base import Robot
    from jetbot_rt.recording.recorder import Recorder
    from jetbot_rt.recording.telemetry import Telemetry
    from jetbot_rt.runtime.loop import LoopStats
    from jetbot_rt.runtime.safety import GuardedDrive, SafeStopLatch
    from jetbot_rt.service.systemd_notify import Notifier


@dataclass(frozen=True)
class LoopFigures:
    ticks: int
    achieved_hz: float
    tick_ms_p50: float
    tick_ms_p99: float
    tick_ms_max: float
    overruns: int

    @classmethod
    def of(cls, stats: LoopStats) -> LoopFigures:
        return cls(ticks=stats.ticks, achieved_hz=round(stats.achieved_hz, 3),
                   tick_ms_p50=round(stats.tick_ms.percentile(50), 3),
                   tick_ms_p99=round(stats.tick_ms.percentile(99), 3),
                   tick_ms_max=round(stats.tick_ms.max, 3), overruns=stats.overruns)


@dataclass
class Summary:
    """How a run ended: the ``end`` event's fields (``fields``) and the lines printed to stdout
    (``str``)."""

    reason: str
    exit_code: int
    rate_hz: float
    loop: LoopFigures | None = None
    counts: dict[str, float] = field(default_factory=dict)
    """The robot's ``stats()`` (``i2c_retried``; the sim's ``travelled_m``, ``goal_distance_m``)."""
    writes_refused: int = 0
    motors: str | None = None
    """Whether the board confirmed the final zero (``GuardedDrive.motors_line``)."""
    motors_confirmed: bool | None = None
    stop_errors: list[str] = field(default_factory=list)
    telemetry_lost: int = 0
    recording: dict[str, Any] | None = None

    def fields(self) -> dict[str, Any]:
        out: dict[str, Any] = {"reason": self.reason, "exit_code": self.exit_code,
                               "cmd": [0.0, 0.0]}
        if self.loop is not None:
            out.update(dataclasses.asdict(self.loop))
        out.update(self.counts)
        if self.writes_refused:
            out["writes_refused"] = self.writes_refused  # late writes the latch blocked
        if self.motors is not None:
            out["motors"] = self.motors
            out["motors_confirmed_zero"] = self.motors_confirmed
        if self.stop_errors:
            out["stop_errors"] = self.stop_errors
        if self.telemetry_lost:
            out["telemetry_lost"] = self.telemetry_lost
        if self.recording is not None:
            out["recording"] = self.recording
        return out

    def __str__(self) -> str:
        lines = ["jetbot-rt run summary"]
        if self.loop is not None:
            loop = self.loop
            lines += [
                f"  ticks        {loop.ticks}",
                f"  rate         {loop.achieved_hz:.2f} Hz (target {self.rate_hz:g} Hz)",
                f"  tick time    p50 {loop.tick_ms_p50:.2f} ms, p99 {loop.tick_ms_p99:.2f} ms",
                f"  overruns     {loop.overruns}",
            ]
        if "travelled_m" in self.counts:  # a scene without a goal piece has no distance
            goal = self.counts.get("goal_distance_m")
            lines.append(f"  travelled    {self.counts['travelled_m']:.2f} m"
                         + (f"; ends {goal:.2f} m from the goal block" if goal is not None
                            else ""))
        if "i2c_retried" in self.counts:
            lines.append(f"  i2c retried  {self.counts['i2c_retried']} transfers")
        if self.telemetry_lost:
            lines.append(f"  telemetry    {self.telemetry_lost} records lost")
        if self.recording is not None:
            lines.append(f"  recording    {recording_line(self.recording)}")
        for error in self.stop_errors:
            lines.append(f"  stop error   {error}")
        if self.motors is not None:
            lines.append(f"  motors       {self.motors}")
        lines.append(f"  stopped      {self.reason}")
        lines.append(f"  exit code    {self.exit_code}")
        return "\n".join(lines)


class Shutdown:
    """The stop phase. What the start-up phases brought up is released by their own exits
    (``Lifecycle.unwind``: watchdog, motors zero, robot, control socket); ``release`` then
    writes zero once more, so the last write of the process is zero. ``finish`` reports the
    run: the ``end`` event and the summary. The start-up phases register what the stop needs
    through the verbs below."""

    def __init__(self, latch: SafeStopLatch, stats: LoopStats, lifecycle: Lifecycle) -> None:
        self.latch = latch
        self.stats = stats
        self.lifecycle = lifecycle
        self._drives: list[GuardedDrive] = []
        self._robots: list[Robot] = []
        self._recorders: list[Recorder] = []
        self._notifiers: list[Notifier] = []

    def zero_last(self, drive: GuardedDrive) -> None:
        """Write zero to ``drive`` after everything else is released, and report its stops."""
        self._drives.append(drive)

    def count_from(self, robot: Robot) -> None:
        """Put the robot's counters (``stats()``) in the summary."""
        self._robots.append(robot)

    def close_with_summary(self, recorder: Recorder) -> None:
        self._recorders.append(recorder)

    def announce_to(self, notifier: Notifier) -> None:
        """Tell the service manager the run is stopping, and why."""
        self._notifiers.append(notifier)

    def release_motors(self) -> None:
        """Motors to zero now (a suspend: the process stops next); bounded, never raises."""
        for drive in self._drives:
            drive.stop()

    def release(self) -> None:
        """Every phase's exit, then zero: the last write of the process. Never raises on a
        phase's failure (says it)."""
        self.lifecycle.unwind()
        self.release_motors()

    def finish(self, telemetry: Telemetry, rate_hz: float) -> Summary:
        """Release everything and report how the run ended."""
        if not self.latch.tripped:
            # Every orderly end trips the latch first (duration, signal, stop request): a loop
            # that ended by itself is a bug, and a bug is a fault.
            self.latch.trip("control loop ended without a stop")
        self.release()
        summary = Summary(
            reason=self.latch.reason or "stopped",
            exit_code=EXIT_SAFE_STOP if self.latch.fault else EXIT_OK,
            rate_hz=rate_hz,
            loop=LoopFigures.of(self.stats) if self.stats.t_start is not None else None,
        )
        for robot in self._robots:
            summary.counts.update(robot.stats())
        for drive in self._drives:
            summary.writes_refused += drive.refused
            summary.stop_errors += drive.stop_errors
            summary.motors = drive.motors_line()
            summary.motors_confirmed = drive.zero_confirmed
            if drive.zero_confirmed is False:
                # Not an orderly end, whatever ended the run: the wheels may still turn.
                summary.exit_code = EXIT_SAFE_STOP
        summary.telemetry_lost = telemetry.lost
        for recorder in self._recorders:
            summary.recording = recorder.close(summary.fields())
        for notifier in self._notifiers:
            notifier.stopping(f"stopping: {summary.reason}")
        telemetry.event("end", **summary.fields())
        telemetry.close()  # bounded: a stalled reader costs records, not the exit
        summary.telemetry_lost = telemetry.lost
        print(summary, flush=True)
        return summary

    def refused(self, telemetry: Telemetry, reason: str) -> None:
        """A start refused for bad input (exit 2): the ``end`` record, nothing printed."""
        fields = {"reason": reason, "exit_code": EXIT_USAGE, "cmd": [0.0, 0.0]}
        telemetry.event("end", **fields)
        for recorder in self._recorders:
            recorder.close(fields)
        telemetry.close()
