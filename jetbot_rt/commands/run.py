"""``jetbot-rt run``, in phases as ros2_control's lifecycle has them: configure (flags and file
to a ``Config``, before anything else) -> services (control socket, service manager) -> load
(the policy) -> prepare (action pipeline, recorder) -> monitor (the live page, if asked) ->
connect (the robot, its drive guarded by the latch) -> start camera -> warm up (first
inference) -> pace gui -> drive (the loop) -> stop (``Shutdown``: every phase's exit in
reverse, motors zero last, the ``Summary``). The phases are in ``run_phases``, their driver in
``lifecycle``.

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

from jetbot_rt.commands.lifecycle import Cancelled, Lifecycle, Phase
from jetbot_rt.commands.run_phases import (
    Connect,
    Drive,
    Load,
    Monitor,
    PaceGui,
    Prepare,
    Services,
    StartCamera,
    WarmUp,
)
from jetbot_rt.commands.shutdown import Shutdown
from jetbot_rt.config.schema import set_value
from jetbot_rt.config.sections import Config, load_config
from jetbot_rt.errors import EXIT_USAGE, Fault, UsageError, first_line
from jetbot_rt.hal.i2c import EMULATOR_FLAG, add_emulator_argument
from jetbot_rt.hal.registry import BACKEND_MODULES
from jetbot_rt.recording.telemetry import Telemetry
from jetbot_rt.runtime.loop import LoopStats
from jetbot_rt.runtime.policy import bundled_policy_path, bundled_task
from jetbot_rt.runtime.safety import SafeStopLatch
from jetbot_rt.service import signals


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
    parser.add_argument("--monitor", metavar="[HOST:]PORT",
                        help="serve the live page (camera, actions, state, a STOP button) on "
                             "this address; HOST defaults to 127.0.0.1, any other needs the "
                             "token (docs/MONITOR.md; default: [monitor] listen, off)")
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
        ("monitor", "listen", getattr(args, "monitor", None), "--monitor"),
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


@dataclass
class RunResult:
    exit_code: int
    reason: str


class Runtime:
    """One ``jetbot-rt run``. ``run()`` enters the phases through ``self.lifecycle`` and
    always ends in the stop phase, ``self.shutdown``."""

    record_meta: dict | None = None
    """More keys for the recording's meta.json (``jetbot-rt drive``: the hand input's)."""
    command = "jetbot-rt run"
    """How its notes name it."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.config = build_config(args)  # configure: bad input fails here, nothing is open
        self.telemetry = Telemetry(self.config.telemetry.path)
        self.latch = SafeStopLatch()
        self.stats = LoopStats()
        self.lifecycle = Lifecycle(self.latch)
        self.shutdown = Shutdown(self.latch, self.stats, self.lifecycle)

    def phases(self) -> list[Phase]:
        services = Services(self)
        load = Load(self)
        prepare = Prepare(self, load)
        self.monitor = Monitor(self, load, prepare)
        connect = Connect(self, load, prepare)
        warm_up = WarmUp(self, load, prepare, connect)
        return [services, load, prepare, self.monitor, connect, StartCamera(connect), warm_up,
                PaceGui(self, connect), Drive(self, services, load, prepare, connect, warm_up)]

    # ---- every way out ------------------------------------------------------------------

    def run(self) -> RunResult:
        """Run, and end safely whatever happens: a ``Fault`` or an unforeseen error is a safe
        stop (exit 3, one line); bad input raises ``UsageError`` (exit 2, motors never moved)."""
        previous_hook = threading.excepthook
        try:
            self._start_and_drive()
            return self.stop()
        finally:
            threading.excepthook = previous_hook

    def _start_and_drive(self) -> None:
        """Through the phases until the driving is over; whatever ends them early leaves the
        latch tripped with the reason, except bad input (raised after the release) and
        ``BaseException``s the runtime does not handle (``KeyboardInterrupt`` outside the
        handlers' reach: raised after the release)."""
        try:
            self._install_signal_handlers()
            threading.excepthook = self._thread_died
            self.lifecycle.run(self.phases())
        except Cancelled:
            pass  # a stop request: the latch holds its reason
        except UsageError as exc:
            self.refuse(exc)
            raise
        except Exception as exc:
            self.latch.trip(self._fault_reason(exc))
        except BaseException:
            self.shutdown.release()
            raise

    def stop(self) -> RunResult:
        """Release everything, report, and return the result (or end the process with it if
        a thread is stuck: ``Lifecycle.exit_if_stuck``; the motors are zero by then)."""
        summary = self.shutdown.finish(self.telemetry, self.config.loop.rate_hz)
        self.lifecycle.exit_if_stuck(summary.exit_code)
        return RunResult(summary.exit_code, summary.reason)

    def refuse(self, exc: UsageError) -> None:
        """Bad input found while starting: release, the ``end`` record; the caller raises
        (the CLI says the line) unless a stuck thread makes this process end here."""
        self.shutdown.release()
        self.shutdown.refused(self.telemetry, str(exc))
        self.lifecycle.exit_if_stuck(EXIT_USAGE, f"jetbot-rt run: error: {exc}")

    @staticmethod
    def _fault_reason(exc: Exception) -> str:
        """A ``Fault``'s own words; anything else is a bug or an unforeseen OS error: still a
        safe stop, said in one line."""
        if isinstance(exc, Fault):
            return str(exc)
        what = f"unexpected error: {type(exc).__name__}: {first_line(exc)}"
        print(f"jetbot-rt run: {what}", file=sys.stderr)
        return what

    # ---- what the phases and the threads call back -------------------------------------

    def log_trip(self, reason: str) -> None:
        self.telemetry.event("safe_stop", reason=reason, fault=self.latch.fault, cmd=[0.0, 0.0])

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

    def status(self) -> str:
        """The service manager's status line while driving."""
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
    # (jetbot_rt.service.signals: WATCHDOG from Python, SIGABRT and the other fatal ones from C).
    signals.enable_stack_dumps()
    return Runtime(args).run().exit_code
