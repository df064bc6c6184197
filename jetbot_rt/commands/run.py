"""``jetbot-rt run``, in phases as ros2_control's lifecycle has them: configure (flags and file
to a ``Config``) -> load (policy, action pipeline, recorder) -> connect (the robot, its drive
guarded by the latch) -> warm up (camera started, first inference) -> drive (the loop) -> stop
(``Shutdown``: everything released, motors zero last, the ``Summary``).

Threads: the control loop runs in its own thread so that the main thread stays free for
signals and can end the process even when a tick hangs inside native code (onnxruntime, a
driver). The watchdog has its own thread. Every way out writes zero to the drive last.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from dataclasses import dataclass
from types import FrameType
from typing import TYPE_CHECKING, Callable, TypeVar

import numpy as np

from jetbot_rt.commands.shutdown import Shutdown
from jetbot_rt.config.sections import Config, load_config, set_value
from jetbot_rt.errors import EXIT_USAGE, Fault, UsageError, first_line
from jetbot_rt.hal import BackendOptions, Robot, make_backend
from jetbot_rt.hal.i2c import EMULATOR_FLAG, add_emulator_argument, emulator_notice
from jetbot_rt.hal.registry import BACKEND_MODULES
from jetbot_rt.recording.recorder import Recorder
from jetbot_rt.recording.recorder import open_for_run as open_recorder
from jetbot_rt.recording.telemetry import Telemetry
from jetbot_rt.runtime.actions import ActionPipeline
from jetbot_rt.runtime.loop import ControlLoop, LoopStats, Safety, Schedule, TickResult
from jetbot_rt.runtime.policy import (
    META_PREFIX,
    OnnxPolicy,
    bundled_policy_path,
    bundled_task,
    resolve_policy_path,
    shown,
)
from jetbot_rt.runtime.safety import GuardedDrive, SafeStopLatch, Watchdog
from jetbot_rt.service import console, signals

if TYPE_CHECKING:
    from jetbot_rt.service.stop_socket import ControlServer
    from jetbot_rt.service.systemd_notify import Notifier

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
    add_emulator_argument(parser)


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
        ("motors", "emulator", getattr(args, "board_emulator", None), EMULATOR_FLAG),
    ]
    for section, key, value, flag in overrides:
        if value is None:
            continue
        try:
            set_value(getattr(config, section), section, key, value)
        except UsageError as exc:
            raise UsageError(f"{flag}: {exc}") from None
    telemetry = config.telemetry.path
    policy = config.policy.path or str(bundled_policy_path(bundled_task(config)))
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


T = TypeVar("T")


@dataclass
class RunResult:
    exit_code: int
    reason: str


@dataclass(frozen=True)
class Loaded:
    """The load phase's result: what bad input could refuse before any device is opened."""

    policy: OnnxPolicy
    actions: ActionPipeline
    recorder: Recorder | None


@dataclass(frozen=True)
class Connected:
    """The connect phase's result: the robot, its drive behind the latch."""

    robot: Robot
    drive: GuardedDrive


class Runtime:
    """One ``jetbot-rt run``. ``run()`` goes through the phases and always ends in the stop
    phase; what each phase brings up is handed to ``self.shutdown``."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.config = build_config(args)  # configure
        self.telemetry = Telemetry(self.config.telemetry.path)
        self.latch = SafeStopLatch()
        self.stats = LoopStats()
        self.shutdown = Shutdown(self.latch, self.stats)
        self.stuck: list[threading.Thread] = []
        """Threads left in native code (a load, a warm-up, a tick): the exit cannot join them."""

    # ---- every way out ------------------------------------------------------------------

    def run(self) -> RunResult:
        """Run, and end safely whatever happens: a ``Fault`` or an unforeseen error is a safe
        stop (exit 3, one line); bad input raises ``UsageError`` (exit 2, motors never moved)."""
        previous_hook = threading.excepthook
        try:
            return self._phases()
        except _Cancelled:
            return self.leave(self.stop())
        except Fault as fault:
            self.latch.trip(str(fault))
            return self.leave(self.stop())
        except UsageError as exc:
            self.shutdown.release()
            self.shutdown.refused(self.telemetry, str(exc))
            if self._stuck():
                # A warm-up stuck in native code makes the interpreter's shutdown abort
                # (SIGABRT, "terminate called without an active exception"): say it as the CLI
                # would, leave.
                print(f"jetbot-rt run: error: {exc}", file=sys.stderr, flush=True)
                console.drain()  # bounded: a stalled reader costs the line, not the exit
                os._exit(EXIT_USAGE)
            raise
        except Exception as exc:  # a bug or an unforeseen OS error: still a safe stop, one line
            what = f"unexpected error: {type(exc).__name__}: {first_line(exc)}"
            print(f"jetbot-rt run: {what}", file=sys.stderr)
            self.latch.trip(what)
            return self.leave(self.stop())
        except BaseException:
            self.shutdown.release()
            raise
        finally:
            threading.excepthook = previous_hook

    def stop(self) -> RunResult:
        summary = self.shutdown.finish(self.telemetry, self.config.loop.rate_hz)
        return RunResult(summary.exit_code, summary.reason)

    def leave(self, result: RunResult) -> RunResult:
        """Return ``result``, or end the process with it if a thread is stuck in native code
        (a load, a warm-up or a tick): the interpreter's shutdown could wait on it or abort
        ("terminate called without an active exception"). The motors are zero by now."""
        if self._stuck():
            console.drain()  # bounded: a stalled reader costs the summary, not the exit
            os._exit(result.exit_code)
        return result

    def _stuck(self) -> bool:
        return any(thread.is_alive() for thread in self.stuck)

    def _phases(self) -> RunResult:
        self._install_signal_handlers()
        threading.excepthook = self._thread_died
        notifier = self._services()
        loaded = self.load()
        self._check_latch()
        connected = self.connect(loaded)
        self._check_latch()
        warmup_ms = self.warm_up(loaded, connected)
        self._check_latch()
        if self.args.gui:
            self.follow_gui_pace(connected.robot)
            self._check_latch()
        return self.drive(loaded, connected, notifier, warmup_ms)

    def _check_latch(self) -> None:
        if self.latch.tripped:
            raise _Cancelled

    # ---- the phases ---------------------------------------------------------------------

    def _services(self) -> Notifier:
        """The service manager's notifier and the control socket (for ``jetbot-rt stop``; one
        per process. A second runtime on the same motor board is refused by the bus's owner
        lock, taken when the robot connects: hal/ownership.py)."""
        from jetbot_rt.service.stop_socket import ControlServer
        from jetbot_rt.service.systemd_notify import Notifier

        notifier = Notifier.from_env()
        self.config.validate_service_watchdog(notifier.watchdog_interval)
        self.shutdown.notifier(notifier)
        control: ControlServer = ControlServer(
            on_stop=lambda reason: self.latch.trip(reason, fault=False)
        )
        control.start()
        self.shutdown.closes(control.close)
        return notifier

    def load(self) -> Loaded:
        """Policy, action pipeline and recorder: everything that can fail on bad input before
        any device is opened."""
        path = resolve_policy_path(self.config.policy.path, bundled_task(self.config))
        limit = self.config.loop.warmup_timeout
        try:
            policy = self._in_worker(
                "load", lambda: OnnxPolicy.load(path, self.config.policy), limit
            )
        except TimeoutError:
            raise UsageError(f"policy {shown(path)}: loading did not finish within {limit:.1f} s") \
                from None
        self._check_latch()
        actions = ActionPipeline.from_config(self.config.actions, policy.max_speed)
        recorder = open_recorder(self.config, self.args.backend, policy, actions.max_speed,
                                 self.telemetry.t0)
        if recorder is not None:
            self.shutdown.recorder(recorder)
        return Loaded(policy, actions, recorder)

    def connect(self, loaded: Loaded) -> Connected:
        """The robot: its motor board opened (every output off), its drive behind the latch."""
        spec = loaded.policy.spec
        options = BackendOptions(frame_size=(spec.width, spec.height), gui=self.args.gui,
                                 task=loaded.policy.metadata.get(META_PREFIX + "task"))
        robot = make_backend(self.args.backend, self.config, options)
        self.shutdown.robot(robot)
        robot.connect()
        drive = GuardedDrive(robot.drive, self.latch)
        self.shutdown.drive(drive)
        # registered after the drive's own zeroing callback: the event is logged once it is done
        self.latch.on_trip(self._log_trip)
        recorder = loaded.recorder
        if recorder is not None:
            self.latch.on_trip(lambda reason: recorder.event(
                "safe_stop", reason=reason, fault=self.latch.fault, cmd=[0.0, 0.0]))
        self.latch.on_trip(lambda _reason: robot.camera.cancel_start())
        drive.stop()  # start from a known state: whatever the board held is cleared
        return Connected(robot, drive)

    def warm_up(self, loaded: Loaded, connected: Connected) -> float:
        """Start the camera, run the policy on a real frame, refuse a policy that is too slow
        or whose first answer is not a finite action (bad input: no motor has moved). Returns
        the fastest inference in ms."""
        policy = loaded.policy
        camera = connected.robot.camera
        camera.start()
        self._check_latch()
        frame = camera.read()
        if frame is None:
            raise UsageError("camera started but delivered no frame")
        period = self.config.loop.period
        limit = self.config.loop.warmup_timeout

        def run_warmup() -> tuple[np.ndarray, list[float]]:
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
            loaded.actions.duties(first)
        except Fault as exc:
            raise UsageError(f"policy {shown(policy.path)}: on the first camera frame: {exc} "
                             "(refused before driving)") from None
        fastest = min(timings)
        if fastest > period:
            raise UsageError(
                f"policy {shown(policy.path)}: too slow for {self.config.loop.rate_hz:g} Hz: "
                f"{fastest * 1e3:.1f} ms per inference > period {period * 1e3:.1f} ms "
                "(lower --rate or use a smaller model)"
            )
        return fastest * 1e3

    def follow_gui_pace(self, robot: Robot) -> None:
        """PyBullet's window on a laptop without a GPU (software OpenGL) makes every world
        step wait for a redraw: hundreds of ms. The simulation then runs slower than real time
        (each tick still advances it by one period) and the watchdog allows for it."""
        slowest = 0.0
        for _ in range(3):  # the motors are at zero: the robot stands still
            t0 = time.perf_counter()
            robot.step(self.config.loop.period)
            slowest = max(slowest, time.perf_counter() - t0)
        loop_cfg = self.config.loop
        if 5 * slowest > loop_cfg.watchdog_timeout_for(robot.simulated):
            loop_cfg.watchdog_timeout = 5 * slowest
            print(f"--gui: a simulation step takes up to {slowest * 1e3:.0f} ms here, so the "
                  f"simulation runs slower than real time; watchdog timeout "
                  f"{loop_cfg.watchdog_timeout:.2f} s", flush=True)

    def drive(self, loaded: Loaded, connected: Connected, notifier: Notifier,
              warmup_ms: float) -> RunResult:
        """The loop in its own thread, supervised from this one until the latch trips."""
        loop_cfg = self.config.loop
        # The sim's default is longer (config.SIM_WATCHDOG_MIN_S): a simulated world stands
        # still while the process is not scheduled, so a desktop's hiccup is no fault there.
        watchdog_timeout = loop_cfg.watchdog_timeout_for(connected.robot.simulated)
        watchdog = Watchdog(self.latch, watchdog_timeout)
        self.shutdown.watchdog(watchdog)
        observers: list[Callable[[TickResult], None]] = []
        if notifier.active:
            observers.append(lambda result: notifier.tick(result.t_end, self._status))
        if loaded.recorder is not None:
            observers.append(loaded.recorder.observe)
        if self.telemetry.enabled:
            observers.append(self.telemetry.observe)
        loop = ControlLoop(
            robot=connected.robot, policy=loaded.policy, actions=loaded.actions,
            safety=Safety(self.latch, connected.drive, watchdog),
            schedule=Schedule(loop_cfg.period, self.config.max_frame_age_s),
            observers=observers, stats=self.stats,
        )
        self.telemetry.rotate()  # the run is known to start: the previous file becomes .1
        self.telemetry.event(
            "start", backend=self.args.backend, policy=loaded.policy.describe(),
            rate_hz=loop_cfg.rate_hz, max_speed=loaded.actions.max_speed,
            watchdog_timeout_s=watchdog_timeout,
            max_frame_age_s=self.config.max_frame_age_s, warmup_ms=round(warmup_ms, 3),
            board_emulator=self.config.motors.emulator,
        )
        notifier.ready(f"ready: policy warmed up ({warmup_ms:.1f} ms), driving")
        loop_thread = threading.Thread(
            target=loop.run, args=(self.args.duration,), name="jetbot-rt-loop", daemon=True
        )
        print(f"driving at {loop_cfg.rate_hz:g} Hz; Ctrl-C or `jetbot-rt stop` to stop", flush=True)
        if self.config.motors.emulator:
            print(emulator_notice(self.config.motors.emulator), flush=True)
        watchdog.start()
        loop_thread.start()
        while loop_thread.is_alive() and not self.latch.tripped:
            loop_thread.join(0.05)
        # The latch is tripped (or the loop ended by itself); give a tick in flight a moment.
        loop_thread.join(max(1.0, 3 * loop_cfg.period))
        if loop_thread.is_alive():
            self.stuck.append(loop_thread)  # stuck in native code, cannot be joined
        return self.leave(self.stop())

    # ---- helpers ------------------------------------------------------------------------

    def _log_trip(self, reason: str) -> None:
        self.telemetry.event("safe_stop", reason=reason, fault=self.latch.fault, cmd=[0.0, 0.0])

    def _in_worker(self, what: str, target: Callable[[], T], limit: float) -> T:
        """Run a start-up step that may sit in native code for minutes (a model load, a
        TensorRT build, the first inference) in a worker thread, so that a stop request or a
        signal ends the start within ``START_POLL_S``, not when the step returns."""
        result: list[T] = []
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
                self.stuck.append(worker)
                raise _Cancelled
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.stuck.append(worker)
                raise TimeoutError
            worker.join(min(remaining, START_POLL_S))
        if error:
            raise error[0]
        return result[0]

    def _install_signal_handlers(self) -> None:
        def handler(signum: int, _frame: FrameType | None) -> None:
            # Python runs this in the main thread between two bytecodes, possibly while that
            # thread holds the drive's lock; tripping here could deadlock.
            threading.Thread(target=self._on_signal, args=(signum,), name="jetbot-rt-signal",
                             daemon=True).start()

        signals.install(handler)

    def _on_signal(self, signum: int) -> None:
        self.latch.trip(f"{signals.name(signum)} received", fault=signum in signals.FAULTING)
        if signum in signals.SUSPENDING:
            # Ctrl-Z: the motors are zero before the process stops (another trip may still be
            # running its callbacks: stop again, it is bounded); on SIGCONT the run ends.
            self.shutdown.release_motors()
            signals.suspend_self()

    def _thread_died(self, args: threading.ExceptHookArgs) -> None:
        """``threading.excepthook``: no thread of the runtime may die silently."""
        if args.exc_type is SystemExit:
            return
        thread = args.thread.name if args.thread is not None else "a thread"
        reason = (f"thread {thread} died: {args.exc_type.__name__}: "
                  f"{first_line(args.exc_value) if args.exc_value else ''}")
        print(f"jetbot-rt run: {reason}", file=sys.stderr, flush=True)
        self.latch.trip(reason)

    def _status(self) -> str:
        stats = self.stats
        if stats.ticks == 0:
            return "starting"
        elapsed = time.monotonic() - (stats.t_start or time.monotonic())
        if elapsed < 1.0:
            return f"driving: {stats.ticks} ticks"
        rate = stats.ticks / elapsed
        return f"driving: {rate:.1f} Hz, {stats.ticks} ticks, {stats.overruns} overruns"


def run(args: argparse.Namespace) -> int:
    # A run that systemd's watchdog ends leaves every thread's stack in the journal
    # (jetbot_rt.signals: WATCHDOG from Python, SIGABRT and the other fatal ones from C).
    signals.enable_stack_dumps()
    return Runtime(args).run().exit_code
