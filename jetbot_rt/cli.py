"""``jetbot-rt``: drive the JetBot (or its simulation) from an ONNX policy, with a safe stop.

Each subcommand lives in its own module of ``jetbot_rt.commands``, imported only when used, so
``jetbot-rt stop`` (what systemd runs after a crash) loads neither onnxruntime nor the camera
code.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import sys

from jetbot_rt import __version__
from jetbot_rt.cli_parser import OneLineParser, plain
from jetbot_rt.errors import EXIT_USAGE, UsageError
from jetbot_rt.service import console, signals
from jetbot_rt.workstation import sim_problem

# subcommand -> (module in jetbot_rt.commands with add_arguments/run, help)
COMMANDS = {
    "run": ("run", "drive the robot (or the simulation) from an ONNX policy"),
    "drive": ("drive", "drive by hand (keyboard, gamepad, scripted), or take over from a "
              "policy while holding a key; record for jetbot-train finetune"),
    "stop": ("stop", "stop a running jetbot-rt and turn the motor outputs off"),
    "check": ("check", "self-test: motor board, camera, policy, providers"),
    "install-service": ("install_service", "install the systemd unit and a default config"),
    "replay": ("replay", "run a policy offline over a recording's frames and compare its mu "
               "with the recorded one (no motor is touched)"),
    "report": ("report", "look at a recording or a telemetry file: run.mp4, run.png and the "
               "summary"),
    "calibrate": ("calibrate", "measure the robot with its camera and a printed marker; write "
                  "the [sim] keys that make the simulator drive like it"),
}


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, str]]:
    parser = OneLineParser(prog="jetbot-rt", description=plain(__doc__.splitlines()[0]))
    parser.add_argument("--version", action="version", version=f"jetbot-rt {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    modules = {}
    for name, (module, help_text) in COMMANDS.items():
        module_name = f"jetbot_rt.commands.{module}"
        command_parser = sub.add_parser(name, help=help_text, description=help_text)
        modules[name] = module_name
        command_parser.set_defaults(_module=module_name)
    return parser, modules


NEVER_INTERRUPTED = {"stop"}
"""Commands a signal never cuts short: ``stop`` (systemd's ExecStopPost, an operator's last
resort) finishes writing the stop, then exits with its own code; SIGKILL still ends it."""
NEVER_BLOCKED = {"run", "drive", "stop", "check", "calibrate"}
"""Commands that touch the motor board: their stdout and stderr never block (a pipe nobody
reads, a terminal stopped by Ctrl-S, a stalled journald), ``jetbot_rt.service.console``. The others
(report, replay...) print as Python does: a reader that is slow is waited for."""


def main(argv: list[str] | None = None) -> int:
    # First: a signal during the imports, the config or the model load ends the command in
    # order (one line, exit 0), not with a KeyboardInterrupt traceback or a silent death.
    # ``jetbot-rt run`` replaces this with its safe-stop handlers before it opens the board.
    command = _command(sys.argv[1:] if argv is None else argv)
    holding = (signals.deferred(raise_after=False) if command in NEVER_INTERRUPTED
               else contextlib.nullcontext())
    with console.unblocked(command in NEVER_BLOCKED):
        try:
            with holding:
                signals.install(signals.raise_interrupted)
                return _main(argv)
        except signals.Interrupted as exc:
            return _stopped_by(command, str(exc))
        except Exception:
            signum = signals.raised_first()
            if signum is None:
                raise
            return _stopped_by(command, signals.name(signum))  # the error replaced Interrupted


def _command(argv: list[str]) -> str:
    """The subcommand ``argv`` names (``run`` for ``jetbot-rt --backend sim``), or ""."""
    if argv and argv[0].startswith("--") and argv[0] not in ("--help", "--version"):
        return "run"
    return next((a for a in argv if not a.startswith("-")), "")


def _stopped_by(command: str, name: str) -> int:
    print(f"jetbot-rt {command}: stopped by {name}".replace("  ", " "), file=sys.stderr,
          flush=True)
    # An orderly end, as a signal while driving is; a self-test cut short did not pass.
    return 1 if command == "check" else 0


def _main(argv: list[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0].startswith("--") and argv[0] not in ("--help", "--version"):
        argv = ["run", *argv]  # `jetbot-rt --backend sim` is `jetbot-rt run --backend sim`
    parser, modules = build_parser()
    # Only the chosen subcommand's module is imported to add its arguments.
    command = next((a for a in argv if not a.startswith("-")), None)
    if command in modules:
        module = importlib.import_module(modules[command])
        subparsers = next(
            a for a in parser._actions if isinstance(a, argparse._SubParsersAction)
        )
        module.add_arguments(subparsers.choices[command])
    args = parser.parse_args(argv)
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args))
    except UsageError as exc:
        print(f"jetbot-rt {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130


def train_main(argv: list[str] | None = None) -> int:
    """``jetbot-train``'s entry point: says in one line when this Python cannot train (the
    robot's 3.8, or a Python without a pybullet wheel) before importing the trainer."""
    problem = sim_problem()
    if problem:
        print(f"jetbot-train: error: {problem}", file=sys.stderr)
        return EXIT_USAGE
    from jetbot_rt.train.cli import main as train_cli

    return train_cli(argv)


if __name__ == "__main__":
    sys.exit(main())
