"""The phases of ``jetbot-rt run`` after configure, in the order ``Runtime`` enters them:
services -> load -> prepare -> monitor -> connect -> start camera -> warm up -> pace gui ->
drive.

Each phase is a ``lifecycle.Phase``: ``enter`` brings its part up (what later phases need is
left on its attributes), ``exit`` releases what ``enter`` opened, also when ``enter`` failed
halfway. Whatever can be refused as bad input (``UsageError``, exit 2) is refused before the
drive phase, so no motor has moved by then.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import TYPE_CHECKING, Callable

import numpy as np

from jetbot_rt.commands.lifecycle import Phase
from jetbot_rt.errors import Fault, UsageError, first_line
from jetbot_rt.hal.base import Robot
from jetbot_rt.hal.i2c import emulator_notice
from jetbot_rt.hal.registry import BackendOptions, make_backend
from jetbot_rt.recording.recorder import Recorder
from jetbot_rt.recording.recorder import open_for_run as open_recorder
from jetbot_rt.runtime.actions import ActionPipeline
from jetbot_rt.runtime.loop import ControlLoop, Policy, Schedule, StopChain, TickResult
from jetbot_rt.runtime.policy import (
    META_PREFIX,
    OnnxPolicy,
    bundled_task,
    resolve_policy_path,
    shown,
)
from jetbot_rt.runtime.safety import GuardedDrive, Watchdog

if TYPE_CHECKING:
    from jetbot_rt.commands.run import Runtime
    from jetbot_rt.monitor.server import MonitorServer
    from jetbot_rt.service.stop_socket import ControlServer
    from jetbot_rt.service.systemd_notify import Notifier


class Services(Phase):
    """The service manager's notifier and the control socket (for ``jetbot-rt stop``; one per
    process. A second runtime on the same motor board is refused by the bus's owner lock,
    taken when the robot connects: hal/ownership.py)."""


    def __init__(self, rt: Runtime) -> None:
        self.rt = rt
        self.notifier: Notifier
        self.control: ControlServer | None = None

    def enter(self) -> None:
        from jetbot_rt.service.stop_socket import ControlServer
        from jetbot_rt.service.systemd_notify import Notifier

        rt = self.rt
        self.notifier = Notifier.from_env()
        rt.config.validate_service_watchdog(self.notifier.watchdog_interval)
        rt.shutdown.announce_to(self.notifier)
        control = ControlServer(on_stop=lambda reason: rt.latch.trip(reason, fault=False))
        control.start()
        self.control = control

    def exit(self) -> None:
        if self.control is not None:
            self.control.close()


class Load(Phase):
    """The policy, loaded in a worker: a stop request ends a load that sits in native code."""


    def __init__(self, rt: Runtime) -> None:
        self.rt = rt
        self.policy: OnnxPolicy

    def enter(self) -> None:
        config = self.rt.config
        path = resolve_policy_path(config.policy.path, bundled_task(config))
        limit = config.loop.warmup_timeout
        try:
            self.policy = self.rt.lifecycle.in_worker(
                "load", lambda: OnnxPolicy.load(path, config.policy), limit
            )
        except TimeoutError:
            raise UsageError(f"policy {shown(path)}: loading did not finish within {limit:.1f} s") \
                from None


class Prepare(Phase):
    """The action pipeline and the recorder: the last refusals of bad input before any device
    is opened."""


    def __init__(self, rt: Runtime, load: Load) -> None:
        self.rt = rt
        self.load = load
        self.actions: ActionPipeline
        self.recorder: Recorder | None = None

    def enter(self) -> None:
        rt = self.rt
        policy = self.load.policy
        self.actions = ActionPipeline.from_config(rt.config.actions, policy.max_speed)
        no_deadband_sim = (rt.args.backend == "sim" and rt.config.sim.deadband == 0
                        and not rt.config.randomize.enabled)
        if policy.calibrated and self.actions.deadband == 0 and not no_deadband_sim:
            # not refused: a robot without a dead-band is one; but the usual case is a robot
            # not calibrated yet, whose motors ignore the policy's smaller commands
            print(f"{rt.command}: note: policy {shown(policy.path)} was trained on a robot "
                  "whose dead-band is lifted ([randomize] deadband_lift) and [actions] "
                  "deadband is 0: set it to this robot's dead-band (jetbot-rt calibrate; "
                  "docs/CALIBRATION.md, step 7)", file=sys.stderr, flush=True)
        self.recorder = open_recorder(rt.config, rt.args.backend, policy, self.actions.max_speed,
                                      rt.telemetry.t0, rt.record_meta)
        if self.recorder is not None:
            rt.shutdown.close_with_summary(self.recorder)


class Monitor(Phase):
    """The live page (``--monitor``, ``[monitor] listen``; jetbot_rt/monitor): bound before the
    robot connects, so a port in use is bad input with the motors never moved. Its observer
    keeps only a reference to the newest tick; a STOP from the page trips the latch as
    ``jetbot-rt stop`` does. Its exit (after the motors' zero) tells the page how the run
    ended."""

    def __init__(self, rt: Runtime, load: Load, prepare: Prepare) -> None:
        self.rt = rt
        self.load = load
        self.prepare = prepare
        self.server: MonitorServer | None = None

    def enter(self) -> None:
        rt = self.rt
        if rt.config.monitor.listen is None:
            return
        from jetbot_rt.monitor import start
        from jetbot_rt.monitor.observer import RunView

        policy = self.load.policy
        view = RunView(rt.latch, rt.stats, rt.config.loop.rate_hz, rt.telemetry.t0,
                       fit=policy.fit, bgr_model=policy.spec.color_order == "BGR",
                       recorder=self.prepare.recorder)
        self.server = start(rt.config.monitor, view,
                            lambda reason: rt.latch.trip(reason, fault=False))

    def observe(self) -> list[Callable[[TickResult], None]]:
        return [self.server.view.observe] if self.server is not None else []

    def exit(self) -> None:
        if self.server is None:
            return
        rt = self.rt
        self.server.view.ended = {"reason": rt.latch.reason, "fault": rt.latch.fault,
                                  "exit_code": 3 if rt.latch.fault else 0}
        self.server.close()


class Connect(Phase):
    """The robot: its motor board opened (every output off), its drive behind the latch."""


    def __init__(self, rt: Runtime, load: Load, prepare: Prepare) -> None:
        self.rt = rt
        self.load = load
        self.prepare = prepare
        self.robot: Robot | None = None
        self.drive: GuardedDrive | None = None

    def enter(self) -> None:
        rt = self.rt
        policy = self.load.policy
        options = BackendOptions(frame_size=(policy.spec.width, policy.spec.height),
                                 gui=rt.args.gui, task=policy.metadata.get(META_PREFIX + "task"))
        robot = self.robot = make_backend(rt.args.backend, rt.config, options)
        rt.shutdown.count_from(robot)
        robot.connect()
        drive = self.drive = GuardedDrive(robot.drive, rt.latch)
        rt.shutdown.zero_last(drive)
        # registered after the drive's own zeroing callback: the event is logged once it is done
        rt.latch.on_trip(rt.log_trip)
        recorder = self.prepare.recorder
        if recorder is not None:
            rt.latch.on_trip(lambda reason: recorder.event(
                "safe_stop", reason=reason, fault=rt.latch.fault, cmd=[0.0, 0.0]))
        rt.latch.on_trip(lambda _reason: robot.camera.cancel_start())
        drive.stop()  # start from a known state: whatever the board held is cleared

    def exit(self) -> None:
        """Motors zero before the board and the camera close."""
        if self.drive is not None:
            self.drive.stop()
        if self.robot is not None:
            self.robot.disconnect()

    @property
    def connected(self) -> tuple[Robot, GuardedDrive]:
        """The robot and its drive, for the phases after this one (entered only after it)."""
        assert self.robot is not None and self.drive is not None
        return self.robot, self.drive


class StartCamera(Phase):
    """The camera, on its own: a stop request while it starts ends the start before warm-up
    (the robot's disconnect stops it)."""

    def __init__(self, connect: Connect) -> None:
        self.connect = connect

    def enter(self) -> None:
        robot, _ = self.connect.connected
        robot.camera.start()


class WarmUp(Phase):
    """Run the policy on a real frame; refuse a policy that is too slow or whose first answer
    is not a finite action (bad input: no motor has moved)."""


    def __init__(self, rt: Runtime, load: Load, prepare: Prepare, connect: Connect) -> None:
        self.rt = rt
        self.load = load
        self.prepare = prepare
        self.connect = connect
        self.fastest_ms = 0.0

    def enter(self) -> None:
        policy = self.load.policy
        robot, _ = self.connect.connected
        frame = robot.camera.read()
        if frame is None:
            raise UsageError("camera started but delivered no frame")
        loop_cfg = self.rt.config.loop
        first, timings = self._infer(frame.image)
        try:
            self.prepare.actions.duties(first)
        except Fault as exc:
            raise UsageError(f"policy {shown(policy.path)}: on the first camera frame: {exc} "
                             "(refused before driving)") from None
        fastest = min(timings)
        if fastest > loop_cfg.period:
            raise UsageError(
                f"policy {shown(policy.path)}: too slow for {loop_cfg.rate_hz:g} Hz: "
                f"{fastest * 1e3:.1f} ms per inference > period {loop_cfg.period * 1e3:.1f} ms "
                "(lower --rate or use a smaller model)"
            )
        self.fastest_ms = fastest * 1e3

    def _infer(self, image: np.ndarray) -> tuple[np.ndarray, list[float]]:
        """The first answer (untimed: the first run allocates) and ``warmup_runs`` timings."""
        policy = self.load.policy
        loop_cfg = self.rt.config.loop

        def run_warmup() -> tuple[np.ndarray, list[float]]:
            first = policy.infer(image)
            timings = []
            for _ in range(loop_cfg.warmup_runs):
                t0 = time.perf_counter()
                policy.infer(image)
                timings.append(time.perf_counter() - t0)
            return first, timings

        limit = loop_cfg.warmup_timeout
        try:
            return self.rt.lifecycle.in_worker("warmup", run_warmup, limit)
        except TimeoutError:
            raise UsageError(
                f"policy {shown(policy.path)}: warm-up inference did not finish within "
                f"{limit:.1f} s"
            ) from None
        except Exception as exc:
            raise UsageError(f"policy {shown(policy.path)}: warm-up inference failed: "
                             f"{first_line(exc)}") from None


class PaceGui(Phase):
    """PyBullet's window on a laptop without a GPU (software OpenGL) makes every world step
    wait for a redraw: hundreds of ms. The simulation then runs slower than real time (each
    tick still advances it by one period) and the watchdog allows for it. Without ``--gui``
    nothing happens."""


    def __init__(self, rt: Runtime, connect: Connect) -> None:
        self.rt = rt
        self.connect = connect

    def enter(self) -> None:
        if not self.rt.args.gui:
            return
        robot, _ = self.connect.connected
        loop_cfg = self.rt.config.loop
        slowest = 0.0
        for _ in range(3):  # the motors are at zero: the robot stands still
            t0 = time.perf_counter()
            robot.step(loop_cfg.period)
            slowest = max(slowest, time.perf_counter() - t0)
        if 5 * slowest > loop_cfg.watchdog_timeout_for(robot.simulated):
            loop_cfg.watchdog_timeout = 5 * slowest
            print(f"--gui: a simulation step takes up to {slowest * 1e3:.0f} ms here, so the "
                  f"simulation runs slower than real time; watchdog timeout "
                  f"{loop_cfg.watchdog_timeout:.2f} s", flush=True)


class Drive(Phase):
    """The loop in its own thread, supervised from the main thread until the latch trips (or
    the loop ends by itself). ``enter`` returns when the driving is over."""


    def __init__(self, rt: Runtime, services: Services, load: Load, prepare: Prepare,
                 connect: Connect, warm_up: WarmUp) -> None:
        self.rt = rt
        self.services = services
        self.load = load
        self.prepare = prepare
        self.connect = connect
        self.warm_up = warm_up
        self.watchdog: Watchdog | None = None

    def enter(self) -> None:
        rt = self.rt
        loop_cfg = rt.config.loop
        robot, drive = self.connect.connected
        # The sim's default is longer (config.SIM_WATCHDOG_MIN_S): a simulated world stands
        # still while the process is not scheduled, so a desktop's hiccup is no fault there.
        watchdog_timeout = loop_cfg.watchdog_timeout_for(robot.simulated)
        watchdog = self.watchdog = Watchdog(rt.latch, watchdog_timeout)
        loop = ControlLoop(
            robot=robot, policy=self.loop_policy(), actions=self.prepare.actions,
            safety=StopChain(rt.latch, drive, watchdog),
            schedule=Schedule(loop_cfg.period, rt.config.max_frame_age_s),
            observers=self._observers(), stats=rt.stats,
        )
        self._announce(watchdog_timeout)
        loop_thread = threading.Thread(
            target=loop.run, args=(rt.args.duration,), name="jetbot-rt-loop", daemon=True
        )
        print(f"driving at {loop_cfg.rate_hz:g} Hz; Ctrl-C or `jetbot-rt stop` to stop", flush=True)
        if rt.config.motors.emulator:
            print(emulator_notice(rt.config.motors.emulator), flush=True)
        watchdog.start()
        loop_thread.start()
        while loop_thread.is_alive() and not rt.latch.tripped:
            loop_thread.join(0.05)
        # The latch is tripped (or the loop ended by itself); give a tick in flight a moment.
        loop_thread.join(max(1.0, 3 * loop_cfg.period))
        if loop_thread.is_alive():
            rt.lifecycle.stuck.append(loop_thread)  # stuck in native code, cannot be joined

    def loop_policy(self) -> Policy:
        """What the loop asks for each tick's action (``jetbot-rt drive``: its arbiter)."""
        return self.load.policy

    def exit(self) -> None:
        """The watchdog first: the stop that follows must not race its thread."""
        if self.watchdog is not None:
            self.watchdog.close()

    def _observers(self) -> list[Callable[[TickResult], None]]:
        rt = self.rt
        notifier = self.services.notifier
        observers: list[Callable[[TickResult], None]] = []
        if notifier.active:
            observers.append(lambda result: notifier.tick(result.t_end, rt.status))
        if self.prepare.recorder is not None:
            observers.append(self.prepare.recorder.observe)
        if rt.telemetry.enabled:
            observers.append(rt.telemetry.observe)
        observers += rt.monitor.observe()
        return observers

    def _announce(self, watchdog_timeout: float) -> None:
        """The run is known to start: the telemetry's ``start`` event (the previous file
        becomes ``.1``) and the service manager's ready."""
        rt = self.rt
        warmup_ms = self.warm_up.fastest_ms
        rt.telemetry.rotate()
        rt.telemetry.event(
            "start", backend=rt.args.backend, policy=self.load.policy.describe(),
            rate_hz=rt.config.loop.rate_hz, max_speed=self.prepare.actions.max_speed,
            watchdog_timeout_s=watchdog_timeout,
            max_frame_age_s=rt.config.max_frame_age_s, warmup_ms=round(warmup_ms, 3),
            board_emulator=rt.config.motors.emulator,
        )
        self.services.notifier.ready(f"ready: policy warmed up ({warmup_ms:.1f} ms), driving")
