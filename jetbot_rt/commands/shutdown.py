"""The stop phase of ``jetbot-rt run``: ``Shutdown`` releases what start-up brought up, in a
fixed order that leaves the motors at zero last, and reports the run as a ``Summary``."""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

from jetbot_rt.errors import EXIT_OK, EXIT_SAFE_STOP, EXIT_USAGE, first_line
from jetbot_rt.recording.recorder import recording_line

if TYPE_CHECKING:
    from jetbot_rt.hal import Robot
    from jetbot_rt.recording.recorder import Recorder
    from jetbot_rt.recording.telemetry import Telemetry
    from jetbot_rt.runtime.loop import LoopStats
    from jetbot_rt.runtime.safety import GuardedDrive, SafeStopLatch, Watchdog
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
        if "travelled_m" in self.counts:
            lines.append(f"  travelled    {self.counts['travelled_m']:.2f} m; ends "
                         f"{self.counts['goal_distance_m']:.2f} m from the goal block")
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
    """The stop phase. Each start-up phase hands it what it brought up; ``finish`` releases it
    all in a fixed order (watchdog, motors zero, closers, motors zero again: the last write of
    the process is zero), then writes the ``end`` event and prints the summary."""

    def __init__(self, latch: SafeStopLatch, stats: LoopStats) -> None:
        self.latch = latch
        self.stats = stats
        self._watchdogs: list[Watchdog] = []
        self._drives: list[GuardedDrive] = []
        self._closers: list[Callable[[], None]] = []
        self._robots: list[Robot] = []
        self._recorders: list[Recorder] = []
        self._notifiers: list[Notifier] = []

    def notifier(self, notifier: Notifier) -> None:
        self._notifiers.append(notifier)

    def closes(self, closer: Callable[[], None]) -> None:
        self._closers.append(closer)

    def recorder(self, recorder: Recorder) -> None:
        self._recorders.append(recorder)

    def robot(self, robot: Robot) -> None:
        self._robots.append(robot)
        self._closers.append(robot.disconnect)

    def drive(self, drive: GuardedDrive) -> None:
        self._drives.append(drive)

    def watchdog(self, watchdog: Watchdog) -> None:
        self._watchdogs.append(watchdog)

    def release_motors(self) -> None:
        """Motors to zero now (a suspend: the process stops next); bounded, never raises."""
        for drive in self._drives:
            drive.stop()

    def release(self) -> None:
        """Everything off and closed; never raises on a closer's failure (says it)."""
        for watchdog in self._watchdogs:
            watchdog.close()
        for drive in self._drives:
            drive.stop()
        for closer in self._closers:
            try:
                closer()
            except Exception as exc:  # cleanup must go on; say what failed
                print(f"jetbot-rt: cleanup: {first_line(exc)}", file=sys.stderr)
        for drive in self._drives:
            drive.stop()  # the last write of the process is zero

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
