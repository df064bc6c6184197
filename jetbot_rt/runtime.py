"""``jetbot-rt run``: assemble config, policy, backend, latch, watchdog and loop; end safely.

Threads: the control loop runs in its own thread so that the main thread stays free for
signals and can end the process even when a tick hangs inside native code (onnxruntime, a
driver). The watchdog has its own thread. Every way out writes zero to the drive last.
"""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from jetbot_rt import signals
from jetbot_rt.actions import ActionPipeline, resolve_max_speed
from jetbot_rt.config import Config, load_config, set_value
from jetbot_rt.errors import EXIT_OK, EXIT_SAFE_STOP, EXIT_USAGE, Fault, UsageError, first_line
from jetbot_rt.hal import BackendOptions, make_backend
from jetbot_rt.hal.registry import BACKEND_MODULES
from jetbot_rt.loop import ControlLoop
from jetbot_rt.policy import OnnxPolicy, bundled_policy_path, shown
from jetbot_rt.recorder import Recorder, recording_line
from jetbot_rt.recorder import open_for_run as open_recorder
from jetbot_rt.safety import GuardedDrive, SafeStopLatch, Watchdog
from jetbot_rt.telemetry import Telemetry

START_POLL_S = 0.02
"""How often the main thread looks at the latch while a start-up step runs in a worker."""


class _Cancelled(BaseException):
    """A stop request (signal, control socket) arrived during start-up."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backend", required=True, choices=sorted(BACKEND_MODULES),
                        help="sim: the PyBullet simulation; real: the JetBot's motors and camera")
    parser.add_argument("--policy", help="ONNX policy (default: the bundled forward policy)")
    parser.add_argument("--config", help="TOML config file (default: every key at its default)")
    parser.add_argument("--rate", type=float,
                        help="control rate in Hz (default: [loop] rate_hz, 30)")
    parser.add_argument("--max-speed", type=float,
                        help="duty at |mu| = 1, in (0, 1] (default: [actions] max_speed, else "
                             "the model's metadata, else 0.1)")
    parser.add_argument("--duration", type=float,
                        help="stop after this many seconds (default: run until stopped)")
    parser.add_argument("--telemetry", help="write JSON Lines telemetry to this file")
    parser.add_argument("--record", metavar="DIR",
                        help="record every tick's frame and record into this new directory "
                             "(docs/RECORDING.md; look at it with jetbot-rt report DIR)")
    parser.add_argument("--gui", action="store_true", help="open PyBullet's window (sim only)")


def same_file(a: str, b: str) -> bool:
    """Whether two paths name one file (a link, ``./x`` and ``x``); for a path that does
    not exist yet, whether they resolve to the same name."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def build_config(args: argparse.Namespace) -> Config:
    config = load_config(args.config)
    overrides = [
        ("loop", "rate_hz", args.rate, "--rate"),
        ("actions", "max_speed", args.max_speed, "--max-speed"),
        ("telemetry", "path", args.telemetry, "--telemetry"),
        ("policy", "path", args.policy, "--policy"),
        ("record", "path", getattr(args, "record", None), "--record"),
    ]
    for section, key, value, flag in overrides:
        if value is None:
            continue
        try:
            set_value(getattr(config, section), section, key, value)
        except UsageError as exc:
            raise UsageError(f"{flag}: {exc}") from None
    telemetry = config.telemetry.path
    policy = config.policy.path or str(bundled_policy_path())
    for what, other in (("--policy", policy), ("--config", args.config)):
        if telemetry and other and same_file(telemetry, other):
            raise UsageError(f"--telemetry {telemetry} is the {what} file; "
                             "telemetry would overwrite it")
    if args.duration is not None and not args.duration > 0:
        raise UsageError(f"--duration must be > 0, got {args.duration:g}")
    if args.gui and args.backend != "sim":
        raise UsageError("--gui needs --backend sim")
    config.validate()
    return config


@dataclass
class RunResult:
    exit_code: int
    reason: str


class Runtime:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.config = build_config(args)
        self.telemetry = Telemetry(self.config.telemetry.path)
        self.latch = SafeStopLatch()
        self.backend: Any = None
        self.drive: GuardedDrive | None = None
        self.loop: ControlLoop | None = None
        self.watchdog: Watchdog | None = None
        self.control: Any = None
        self.notifier: Any = None
        self.stuck_thread: threading.Thread | None = None
        self.recorder: Recorder | None = None

    def _log_trip(self, reason: str) -> None:
        self.telemetry.event("safe_stop", reason=reason, fault=self.latch.fault, cmd=[0.0, 0.0])

    def _policy_path(self) -> Path:
        if self.config.policy.path:
            return Path(self.config.policy.path)
        bundled = bundled_policy_path()
        if not bundled.is_file():
            raise UsageError("no bundled policy in this installation; pass --policy FILE.onnx")
        return bundled

    def _in_worker(self, what: str, target: Any, limit: float) -> Any:
        """Run a start-up step that may sit in native code for minutes (a model load, a
        TensorRT build, the first inference) in a worker thread, so that a stop request or a
        signal ends the start within ``START_POLL_S``, not when the step returns."""
        result: list[Any] = []
        error: list[BaseException] = []

        def body() -> None:
            try:
                result.append(target())
            except BaseException as exc:
                error.append(exc)

        worker = threading.Thread(target=body, name=f"jetbot-rt-{what}", daemon=True)
        worker.start()
        deadline = time.monotonic() + limit
        while worker.is_alive():
            if self.latch.tripped:
                self.stuck_thread = worker
                raise _Cancelled
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.stuck_thread = worker
                raise TimeoutError
            worker.join(min(remaining, START_POLL_S))
        if error:
            raise error[0]
        return result[0]

    def load_policy(self) -> OnnxPolicy:
        path = self._policy_path()
        limit = self.config.loop.warmup_timeout
        try:
            return self._in_worker(
                "load", lambda: OnnxPolicy.load(path, self.config.policy), limit
            )
        except TimeoutError:
            raise UsageError(f"policy {shown(path)}: loading did not finish within {limit:.1f} s") \
                from None

    def prepare(self, policy: OnnxPolicy) -> None:
        """Everything else that can fail on bad input, before any motor is touched."""
        spec = policy.spec
        self.actions = ActionPipeline(
            max_speed=resolve_max_speed(self.config.actions.max_speed, policy.max_speed),
            trim=(self.config.actions.trim[0], self.config.actions.trim[1]),
            sign=(self.config.actions.sign[0], self.config.actions.sign[1]),
        )
        self.recorder = open_recorder(self.config, self.args.backend, policy,
                                      self.actions.max_speed, self.telemetry.t0)
        options = BackendOptions(frame_size=(spec.width, spec.height), gui=self.args.gui)
        self.backend = make_backend(self.args.backend, self.config, options)
        self.drive = GuardedDrive(self.backend.drive, self.latch)
        # registered after the drive's own zeroing callback: the event is logged once it is done
        self.latch.on_trip(self._log_trip)
        if self.recorder is not None:
            self.latch.on_trip(self._record_trip)
        self.latch.on_trip(lambda _reason: self.backend.camera.cancel_start())

    def _record_trip(self, reason: str) -> None:
        assert self.recorder is not None
        self.recorder.event("safe_stop", reason=reason, fault=self.latch.fault, cmd=[0.0, 0.0])

    def warm_up(self, policy: OnnxPolicy) -> None:
        """Start the camera, run the policy on a real frame, refuse a policy that is too slow
        or whose first answer is not a finite action (bad input: no motor has moved)."""
        camera = self.backend.camera
        camera.start()
        if self.latch.tripped:
            raise _Cancelled
        frame = camera.read()
        if frame is None:
            raise UsageError("camera started but delivered no frame")
        period = self.config.loop.period
        limit = self.config.loop.warmup_timeout

        def run_warmup() -> tuple[Any, list[float]]:
            first = policy.infer(frame.image)  # first run allocates; not timed
            timings = []
            for _ in range(self.config.loop.warmup_runs):
                t0 = time.perf_counter()
                policy.infer(frame.image)
                timings.append(time.perf_counter() - t0)
            return first, timings

        try:
            first, timings = self._in_worker("warmup", run_warmup, limit)
        except TimeoutError:
            raise UsageError(
                f"policy {shown(policy.path)}: warm-up inference did not finish within "
                f"{limit:.1f} s"
            ) from None
        except Exception as exc:
            raise UsageError(f"policy {shown(policy.path)}: warm-up inference failed: "
                             f"{first_line(exc)}") from None
        try:
            self.actions.duties(first)
        except Fault as exc:
            raise UsageError(f"policy {shown(policy.path)}: on the first camera frame: {exc} "
                             "(refused before driving)") from None
        fastest = min(timings)
        self.warmup_ms = fastest * 1e3
        if fastest > period:
            raise UsageError(
                f"policy {shown(policy.path)}: too slow for {self.config.loop.rate_hz:g} Hz: "
                f"{fastest * 1e3:.1f} ms per inference > period {period * 1e3:.1f} ms "
                "(lower --rate or use a smaller model)"
            )

    def follow_gui_pace(self) -> None:
        """PyBullet's window on a laptop without a GPU (software OpenGL) makes every world
        step wait for a redraw: hundreds of ms. The simulation then runs slower than real time
        (each tick still advances it by one period) and the watchdog allows for it."""
        slowest = 0.0
        for _ in range(3):  # the motors are at zero: the robot stands still
            t0 = time.perf_counter()
            self.backend.advance(self.config.loop.period)
            slowest = max(slowest, time.perf_counter() - t0)
        loop_cfg = self.config.loop
        if 5 * slowest > loop_cfg.watchdog_timeout_s:
            loop_cfg.watchdog_timeout = 5 * slowest
            print(f"--gui: a simulation step takes up to {slowest * 1e3:.0f} ms here, so the "
                  f"simulation runs slower than real time; watchdog timeout "
                  f"{loop_cfg.watchdog_timeout:.2f} s", flush=True)

    def _install_signal_handlers(self) -> None:
        def handler(signum: int, _frame: Any) -> None:
            # Python runs this in the main thread between two bytecodes, possibly while that
            # thread holds the drive's lock; tripping here could deadlock.
            threading.Thread(target=self._on_signal, args=(signum,), name="jetbot-rt-signal",
                             daemon=True).start()

        signals.install(handler)

    def _on_signal(self, signum: int) -> None:
        self.latch.trip(f"{signals.name(signum)} received", fault=False)
        if signum in signals.SUSPENDING:
            # Ctrl-Z: the motors are zero before the process stops (another trip may still be
            # running its callbacks: stop again, it is bounded); on SIGCONT the run ends.
            if self.drive is not None:
                self.drive.stop()
            signals.suspend_self()

    def _thread_died(self, args: Any) -> None:
        """``threading.excepthook``: no thread of the runtime may die silently."""
        if args.exc_type is SystemExit:
            return
        thread = args.thread.name if args.thread is not None else "a thread"
        reason = (f"thread {thread} died: {args.exc_type.__name__}: "
                  f"{first_line(args.exc_value) if args.exc_value else ''}")
        print(f"jetbot-rt run: {reason}", file=sys.stderr, flush=True)
        self.latch.trip(reason)

    def _status(self) -> str:
        stats = self.loop.stats if self.loop else None
        if stats is None or stats.ticks == 0:
            return "starting"
        elapsed = time.monotonic() - (stats.t_start or time.monotonic())
        if elapsed < 1.0:
            return f"driving: {stats.ticks} ticks"
        rate = stats.ticks / elapsed
        return f"driving: {rate:.1f} Hz, {stats.ticks} ticks, {stats.overruns} overruns"

    def run(self) -> RunResult:
        from jetbot_rt.control import ControlServer
        from jetbot_rt.notify import Notifier

        self._install_signal_handlers()
        threading.excepthook = self._thread_died
        self.notifier = Notifier.from_env()
        self.config.validate_service_watchdog(self.notifier.watchdog_interval)
        try:
            # The control socket is for `jetbot-rt stop` to talk to this runtime; one per
            # process. A second runtime on the same motor board is refused by the bus's owner
            # lock, taken before the board is first written (hal/ownership.py).
            self.control = ControlServer(
                on_stop=lambda reason: self.latch.trip(reason, fault=False)
            )
            self.control.start()
            policy = self.load_policy()
            if self.latch.tripped:
                raise _Cancelled
            self.prepare(policy)
            assert self.drive is not None
            self.drive.stop()  # start from a known state: whatever the board held is cleared
            if self.latch.tripped:
                raise _Cancelled
            self.warm_up(policy)
            if self.args.gui and not self.latch.tripped:
                self.follow_gui_pace()
            if self.latch.tripped:
                raise _Cancelled
            return self._drive(policy)
        except _Cancelled:
            return self.leave(self._finish())
        except BaseException:
            self._final_stop()
            raise

    def leave(self, result: RunResult) -> RunResult:
        """Return ``result``, or end the process with it if a thread is stuck in native code
        (a load, a warm-up or a tick): the interpreter's shutdown could wait on it or abort
        ("terminate called without an active exception"). The motors are zero by now."""
        stuck = self.stuck_thread
        if stuck is not None and stuck.is_alive():
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(result.exit_code)
        return result

    def _drive(self, policy: OnnxPolicy) -> RunResult:
        loop_cfg = self.config.loop
        self.watchdog = Watchdog(self.latch, loop_cfg.watchdog_timeout_s)
        self.loop = ControlLoop(
            camera=self.backend.camera,
            policy=policy,
            actions=self.actions,
            drive=self.drive,
            latch=self.latch,
            watchdog=self.watchdog,
            telemetry=self.telemetry,
            period=loop_cfg.period,
            max_frame_age=self.config.max_frame_age_s,
            advance=self.backend.advance,
            extra_telemetry=self.backend.telemetry,
            on_tick_done=lambda now: self.notifier.tick(now, self._status),
            observers=[self.recorder.observe] if self.recorder is not None else [],
        )
        self.telemetry.rotate()  # the run is known to start: the previous file becomes .1
        self.telemetry.event(
            "start", backend=self.args.backend, policy=policy.describe(),
            rate_hz=loop_cfg.rate_hz, max_speed=self.actions.max_speed,
            watchdog_timeout_s=loop_cfg.watchdog_timeout_s,
            max_frame_age_s=self.config.max_frame_age_s, warmup_ms=round(self.warmup_ms, 3),
        )
        self.notifier.ready(f"ready: policy warmed up ({self.warmup_ms:.1f} ms), driving")
        loop_thread = threading.Thread(
            target=self.loop.run, args=(self.args.duration,), name="jetbot-rt-loop", daemon=True
        )
        print(f"driving at {loop_cfg.rate_hz:g} Hz; Ctrl-C or `jetbot-rt stop` to stop", flush=True)
        self.watchdog.start()
        loop_thread.start()
        while loop_thread.is_alive() and not self.latch.tripped:
            loop_thread.join(0.05)
        # The latch is tripped (or the loop ended by itself); give a tick in flight a moment.
        loop_thread.join(max(1.0, 3 * loop_cfg.period))
        if loop_thread.is_alive():
            self.stuck_thread = loop_thread  # stuck in native code, cannot be joined
        return self.leave(self._finish())

    def _final_stop(self) -> None:
        if self.watchdog is not None:
            self.watchdog.close()
        if self.drive is not None:
            self.drive.stop()
        for closer in (
            getattr(self.backend, "camera", None) and self.backend.camera.stop,
            self.control and self.control.close,
            self.backend and self.backend.close,
        ):
            if closer:
                try:
                    closer()
                except Exception as exc:  # cleanup must go on; say what failed
                    print(f"jetbot-rt: cleanup: {first_line(exc)}", file=sys.stderr)
        if self.drive is not None:
            self.drive.stop()  # the last write of the process is zero

    def _finish(self) -> RunResult:
        if not self.latch.tripped:
            # Every orderly end trips the latch first (duration, signal, stop request): a loop
            # that ended by itself is a bug, and a bug is a fault.
            self.latch.trip("control loop ended without a stop")
        self._final_stop()
        fault = self.latch.fault
        exit_code = EXIT_SAFE_STOP if fault else EXIT_OK
        reason = self.latch.reason or "stopped"
        stats = self.loop.stats if self.loop else None
        summary: dict[str, Any] = {"reason": reason, "exit_code": exit_code, "cmd": [0.0, 0.0]}
        if stats is not None:
            summary.update(
                ticks=stats.ticks,
                achieved_hz=round(stats.achieved_hz, 3),
                tick_ms_p50=round(stats.tick_ms.percentile(50), 3),
                tick_ms_p99=round(stats.tick_ms.percentile(99), 3),
                tick_ms_max=round(stats.tick_ms.max, 3),
                overruns=stats.overruns,
            )
        if self.backend is not None and self.backend.counters is not None:
            summary.update(self.backend.counters())
        if self.drive is not None and self.drive.refused:
            summary["writes_refused"] = self.drive.refused  # late writes the latch blocked
        if self.drive is not None and self.drive.stop_errors:
            summary["stop_errors"] = self.drive.stop_errors
        if self.telemetry.lost:
            summary["telemetry_lost"] = self.telemetry.lost
        if self.recorder is not None:
            summary["recording"] = self.recorder.close(dict(summary))
        if self.notifier is not None:
            self.notifier.stopping(f"stopping: {reason}")
        self.telemetry.event("end", **summary)
        self.telemetry.close()  # bounded: a stalled reader costs records, not the exit
        if self.telemetry.lost:
            summary["telemetry_lost"] = self.telemetry.lost
        print_summary(summary, self.config.loop.rate_hz)
        return RunResult(exit_code, reason)


def print_summary(summary: dict[str, Any], rate_hz: float) -> None:
    lines = ["jetbot-rt run summary"]
    if "ticks" in summary:
        lines += [
            f"  ticks        {summary['ticks']}",
            f"  rate         {summary['achieved_hz']:.2f} Hz (target {rate_hz:g} Hz)",
            f"  tick time    p50 {summary['tick_ms_p50']:.2f} ms, "
            f"p99 {summary['tick_ms_p99']:.2f} ms",
            f"  overruns     {summary['overruns']}",
        ]
    if "travelled_m" in summary:
        lines.append(f"  travelled    {summary['travelled_m']:.2f} m; ends "
                     f"{summary['goal_distance_m']:.2f} m from the goal block")
    if "i2c_retried" in summary:
        lines.append(f"  i2c retried  {summary['i2c_retried']} transfers")
    if summary.get("telemetry_lost"):
        lines.append(f"  telemetry    {summary['telemetry_lost']} records lost")
    if "recording" in summary:
        lines.append(f"  recording    {recording_line(summary['recording'])}")
    for error in summary.get("stop_errors", []):
        lines.append(f"  stop error   {error}")
    lines.append(f"  stopped      {summary['reason']}")
    lines.append(f"  exit code    {summary['exit_code']}")
    print("\n".join(lines), flush=True)


def run(args: argparse.Namespace) -> int:
    # A hang that systemd's watchdog ends with SIGABRT leaves every thread's stack in the journal.
    with contextlib.suppress(ValueError, OSError, AttributeError):  # stderr without a file
        faulthandler.enable(file=sys.__stderr__)
    runtime = Runtime(args)
    previous_hook = threading.excepthook
    try:
        return runtime.run().exit_code
    except Fault as fault:
        runtime.latch.trip(str(fault))
        return runtime.leave(runtime._finish()).exit_code
    except UsageError as exc:
        runtime.telemetry.event("end", reason=str(exc), exit_code=2, cmd=[0.0, 0.0])
        if runtime.recorder is not None:
            runtime.recorder.close({"reason": str(exc), "exit_code": 2, "cmd": [0.0, 0.0]})
        runtime.telemetry.close()
        if runtime.stuck_thread is not None and runtime.stuck_thread.is_alive():
            # A warm-up stuck in native code makes the interpreter's shutdown abort (SIGABRT,
            # "terminate called without an active exception"): say it as the CLI would, leave.
            print(f"jetbot-rt run: error: {exc}", file=sys.stderr, flush=True)
            sys.stdout.flush()
            os._exit(EXIT_USAGE)
        raise
    except Exception as exc:  # a bug or an unforeseen OS error: still a safe stop, one line
        print(f"jetbot-rt run: unexpected error: {type(exc).__name__}: {first_line(exc)}",
              file=sys.stderr)
        runtime.latch.trip(f"unexpected error: {type(exc).__name__}: {first_line(exc)}")
        return runtime.leave(runtime._finish()).exit_code
    finally:
        threading.excepthook = previous_hook
