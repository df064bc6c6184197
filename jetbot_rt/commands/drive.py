"""``jetbot-rt drive``: a person drives the robot (or the simulation), or takes over from a
policy while holding a key or button (human-gated DAgger); ``--record`` keeps who drove each
tick, for ``jetbot-train finetune``. docs/DRIVE.md.

It is ``jetbot-rt run`` with two phases more, not a second loop: the same configure, services,
load, prepare, monitor, connect, camera, warm-up and stop phases, the same latch, watchdog,
board owner lock, signals and exit codes. ``Inputs`` opens the hand input before the robot
connects (a missing terminal or device is bad input: exit 2, motors never moved); ``HandDrive``
is the drive phase with the ``Arbiter`` as the loop's policy and the tick records marked with
who drove. In the simulator an episode that ends (success, failure, time limit) gives way to a
new scene, so that minutes of driving give many scenes.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import Any, Callable

from jetbot_rt.commands.lifecycle import Phase
from jetbot_rt.commands.run import Runtime
from jetbot_rt.commands.run import add_arguments as add_run_arguments
from jetbot_rt.commands.run_phases import Connect, Drive, Load, Prepare
from jetbot_rt.errors import UsageError
from jetbot_rt.runtime.loop import Policy, TickResult
from jetbot_rt.runtime.policy import META_PREFIX
from jetbot_rt.service import signals
from jetbot_rt.teleop.hand import DEADMAN_S, MAX_DEADMAN_S, Arbiter, HandInput

INPUTS = ("keyboard", "gamepad", "page", "scripted")
DEFAULT_GAMEPAD = "/dev/input/js0"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_arguments(parser)
    for action in parser._actions:
        if action.dest == "policy":
            action.help = ("ONNX policy that drives while the person does not hold the "
                           "take-over key or button (default: none, the person drives)")
    parser.add_argument("--input", required=True, choices=INPUTS,
                        help="keyboard: the terminal on stdin (ssh -t works); gamepad: a Linux "
                             "joystick device; page: the monitor's page ([monitor] drive = "
                             "true); scripted: the sim task's expert as the person")
    parser.add_argument("--deadman", type=float, default=DEADMAN_S,
                        help=f"seconds a hand command stays valid without a new key repeat "
                             f"or device event, at most {MAX_DEADMAN_S:g}")
    parser.add_argument("--gamepad-device", default=DEFAULT_GAMEPAD,
                        help="the joystick device for --input gamepad (kernel joystick API)")


def check_arguments(args: argparse.Namespace) -> None:
    if not 0 < args.deadman <= MAX_DEADMAN_S:
        # repr, not :g: 0.30000001 shown as 0.3 would read as a value inside the bound
        raise UsageError(f"--deadman must be in (0, {MAX_DEADMAN_S:g}] s, got {args.deadman!r}")
    if args.input == "scripted" and args.backend != "sim":
        raise UsageError("--input scripted is the simulator's stand-in for a person: it "
                         "needs --backend sim")


class Inputs(Phase):
    """The hand input, validated and opened right after the policy loaded, before the
    recording or any device: a missing terminal or device, a task without an expert, a page
    input without the page is bad input with nothing written. Closed (the terminal's mode
    given back) at the stop."""

    def __init__(self, rt: DriveRuntime, load: Load) -> None:
        self.rt = rt
        self.load = load
        self.hand: HandInput | None = None

    def enter(self) -> None:
        rt, args = self.rt, self.rt.args
        if args.input == "keyboard":
            from jetbot_rt.teleop.keyboard import KeyboardInput

            self.hand = KeyboardInput(sys.stdin.fileno(), args.deadman)
        elif args.input == "page":
            if rt.config.monitor.listen is None or not rt.config.monitor.drive:
                raise UsageError("--input page drives from the monitor's page: it needs "
                                 "--monitor (or [monitor] listen) and [monitor] drive = true")
            # the PageInput itself needs the monitor's server: StartInputs makes it
        elif args.input == "gamepad":
            from jetbot_rt.teleop.gamepad import GamepadInput

            self.hand = GamepadInput(args.gamepad_device, args.deadman)
        else:
            from jetbot_rt.tasks import load_task
            from jetbot_rt.teleop.scripted import ScriptedInput

            self.hand = ScriptedInput(load_task(rt.task_name(self.load)), rt.policy_drives,
                                      rt.config.sim.seed)
        if self.hand is not None:  # the scripted person's reaction, noise and rules too
            rt.record_meta["drive"].update(self.hand.describe())

    def exit(self) -> None:
        if self.hand is not None:
            self.hand.close()


class StartInputs(Phase):
    """The hand input starts listening just before the robot connects. Lost: the latch trips
    (a fault, exit 3), then the ``input_lost`` event; a quit key is an orderly stop
    (exit 0)."""

    def __init__(self, rt: DriveRuntime, inputs: Inputs) -> None:
        self.rt = rt
        self.inputs = inputs

    def enter(self) -> None:
        rt = self.rt
        if rt.args.input == "page":
            from jetbot_rt.teleop.page import PageInput

            server = rt.monitor.server
            assert server is not None  # Inputs refused a page input without [monitor] listen
            self.inputs.hand = PageInput(server, rt.args.deadman)
        hand = self.inputs.hand
        assert hand is not None
        hand.on_lost = self._lost
        hand.on_quit = lambda reason: rt.latch.trip(reason, fault=False)
        hand.start()

    def _lost(self, reason: str) -> None:
        rt = self.rt
        rt.latch.trip(f"input lost: {reason}")  # motors zero first, then say so
        rt.event("input_lost", reason=reason)


class HandDrive(Drive):
    """The drive phase with the arbiter as the loop's policy; every tick's record carries
    ``driver`` (policy or human), ``human`` (the person's command in force, or null) and
    ``policy_mu`` (where a policy ran); ``takeover`` / ``handback`` events mark the switches."""

    def __init__(self, base: Drive, inputs: Inputs) -> None:
        super().__init__(base.rt, base.services, base.load, base.prepare, base.connect,
                         base.warm_up)
        self.inputs = inputs
        self.arbiter: Arbiter | None = None
        self.episodes: Any = None

    def enter(self) -> None:
        rt = self.rt
        hand = self.inputs.hand
        assert hand is not None
        robot, _ = self.connect.connected
        self.arbiter = Arbiter(self.load.policy if rt.policy_drives else None, hand)
        if robot.simulated:
            from jetbot_rt.tasks import load_task
            from jetbot_rt.teleop.scripted import ScriptedInput, SimEpisodes

            if isinstance(hand, ScriptedInput):
                hand.bind(robot.world)  # type: ignore[attr-defined]
            self.episodes = SimEpisodes(robot, load_task(rt.task_name(self.load)), rt.config,
                                        self._episode_end)
        rt.drive_phase = self
        super().enter()

    def loop_policy(self) -> Policy:
        assert self.arbiter is not None
        return self.arbiter

    def _episode_end(self, episode: int, success: bool, reason: str, steps: int) -> None:
        self.rt.event("episode_end", episode=episode, success=success, reason=reason,
                      steps=steps)
        reset = getattr(self.inputs.hand, "reset", None)
        if reset is not None:
            reset()

    def _observers(self) -> list[Callable[[TickResult], None]]:
        inner = super()._observers()
        arbiter = self.arbiter
        episodes = self.episodes
        rt = self.rt
        assert arbiter is not None

        def observe(result: TickResult) -> None:
            marked = dataclasses.replace(result, extra={**result.extra, **arbiter.marks})
            for observer in inner:
                observer(marked)
            if arbiter.switched is not None:
                rt.event(arbiter.switched, driver=arbiter.driver, tick=result.tick)
            if episodes is not None:
                episodes.observe(marked)

        return [observe]


class DriveRuntime(Runtime):
    """``run``'s runtime with the hand input: ``phases`` are run's, ``Inputs`` before
    ``Prepare`` (which opens the recording), ``StartInputs`` before ``Connect`` and
    ``HandDrive`` in place of ``Drive``."""

    command = "jetbot-rt drive"

    def __init__(self, args: argparse.Namespace) -> None:
        check_arguments(args)
        self.policy_drives = args.policy is not None
        self.record_meta: dict = {"source": "jetbot-rt drive",
                                  "drive": {"input": args.input, "deadman_s": args.deadman,
                                            "policy_drives": args.policy is not None}}
        self.drive_phase: HandDrive | None = None
        self.prepare_phase: Prepare | None = None
        super().__init__(args)

    def task_name(self, load: Load) -> str:
        """The task of the scene (the sim backend's ``scene_task``): ``[sim] task``, else the
        policy's metadata, else forward."""
        from jetbot_rt.tasks import DEFAULT_TASK

        named = load.policy.metadata.get(META_PREFIX + "task")
        return self.config.sim.task or (named if named and named.isidentifier()
                                        else DEFAULT_TASK)

    def phases(self) -> list[Phase]:
        phases = super().phases()
        load = next(p for p in phases if isinstance(p, Load))
        prepare = next(p for p in phases if isinstance(p, Prepare))
        self.prepare_phase = prepare
        inputs = Inputs(self, load)
        phases.insert(phases.index(prepare), inputs)
        connect = next(i for i, p in enumerate(phases) if isinstance(p, Connect))
        phases.insert(connect, StartInputs(self, inputs))
        drive = next(i for i, p in enumerate(phases) if isinstance(p, Drive))
        phases[drive] = HandDrive(phases[drive], inputs)  # type: ignore[arg-type]
        return phases

    def event(self, name: str, **fields: Any) -> None:
        """An event in the telemetry and the recording (from any thread: neither blocks)."""
        self.telemetry.event(name, **fields)
        recorder = self.prepare_phase.recorder if self.prepare_phase is not None else None
        if recorder is not None:
            recorder.event(name, **fields)

    def summary_line(self) -> str | None:
        phase = self.drive_phase
        if phase is None or phase.arbiter is None or not phase.arbiter.ticks:
            return None
        arbiter = phase.arbiter
        line = (f"drive: {arbiter.ticks} ticks, {arbiter.human_ticks} by hand "
                f"({arbiter.human_ticks / arbiter.ticks:.0%})")
        if self.policy_drives:
            line += f", {arbiter.takeovers} takeovers"
        if phase.episodes is not None:
            line += (f"; {phase.episodes.episode} episodes ended, "
                     f"{phase.episodes.successes} successful")
        return line


def run(args: argparse.Namespace) -> int:
    signals.enable_stack_dumps()
    runtime = DriveRuntime(args)
    result = runtime.run()
    line = runtime.summary_line()
    if line:
        print(line, flush=True)
    return result.exit_code
