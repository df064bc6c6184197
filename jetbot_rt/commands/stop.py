"""``jetbot-rt stop``: turn every motor output off for good, then latch running runtimes' safe
stop, confirm, report.

This is what systemd runs after every end of the service (``ExecStopPost``), a crash or a
watchdog kill included, so it needs nothing but the config and the I2C bus: no camera, no
policy, no onnxruntime. In this order:

1. Which board: the config's ``[motors]`` bus and address (read in bounded time). If the
   config cannot be read, the board the last runtime recorded in its runtime directory
   (``runtime_dir.read_board_record``: read as untrusted), else the defaults, saying so.
2. The stop, before any other process is asked anything: every output full-off, then the
   oscillator off (SLEEP), in one combined I2C transaction. Asleep, the chip holds its
   outputs off whatever a process writes to its LED registers (``hal/motors.py``); a
   runtime's next write finds it asleep, which is a fault, and ends in its safe stop
   (exit 3). Nothing any other process does can delay this step.
3. Every runtime whose control socket it trusts is asked, all at once, to latch its safe stop
   (an orderly end), for at most ``ASK_TOTAL_S`` in all (``stop_socket.request_stop``).
   Directories and sockets of other users, and links, are not asked; one line names them.
   If step 2 failed (a burst of bus errors), the stop is written once more now.
4. Confirmation: it waits (at most ``CONFIRM_S``) until no process owns the bus (the owner's
   ``flock``, ``hal/ownership.py``), then reads MODE1 back. Success only if the chip still
   sleeps (nobody set it up again) and nobody owns the bus.

Exit 0 when the motors are confirmed off; 1 when the board cannot be reached or the stop
cannot be confirmed (the line names the process that still owns the bus); 2 when the config
is bad (the stop is still written, on the recorded or the default board).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable

from jetbot_rt.config.sections import MotorsConfig, load_config
from jetbot_rt.errors import EXIT_USAGE, UsageError, first_line
from jetbot_rt.hal.i2c import I2CBus, I2CFault, add_emulator_argument, emulator_notice
from jetbot_rt.hal.motors import read_mode1, stop_and_sleep
from jetbot_rt.hal.ownership import bus_device, describe, owned, owner_pids
from jetbot_rt.hal.pca9685 import MODE1_SLEEP
from jetbot_rt.service.runtime_dir import read_board_record
from jetbot_rt.service.stop_socket import ASK_TOTAL_S, request_stop

__all__ = ["ASK_TOTAL_S", "CONFIRM_S", "add_arguments", "run"]

EXIT_BOARD_UNREACHABLE = 1
CONFIRM_S = 3.0
"""How long ``stop`` waits for the bus's owner to end: a runtime it could not reach ends at
its next write (one period, then its exit: camera child, telemetry)."""
MAX_NAMED = 4
"""Paths named in a line (unreachable sockets, what was ignored); the rest are counted."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML config file (for [motors] bus and address)")
    add_emulator_argument(parser)


def _motors(path: str | None) -> tuple[MotorsConfig, str | None]:
    """The config's [motors]; if the config cannot be read, the board the last runtime
    recorded, else the defaults, and why. Never raises."""
    try:
        return load_config(path).motors, None
    except UsageError as exc:
        error = str(exc)
    except Exception as exc:  # the stop must go out whatever the config holds
        error = f"config {path}: {type(exc).__name__}: {first_line(exc)}"
    record, why = read_board_record()  # never raises: every problem is a reason
    if record is None:
        return MotorsConfig(), f"{error}; using the default bus and address ({why})"
    motors = MotorsConfig(i2c_bus=record.i2c_bus, address=record.address,
                          emulator=record.emulator)
    return motors, f"{error}; using the board the runtime recorded in {record.path}"


def _write_stop(motors: MotorsConfig, write: Callable[[I2CBus, int], None]) -> str | None:
    """The hardware stop; None when written, else why not."""
    try:
        with I2CBus.for_motors(motors) as bus:
            write(bus, motors.address)
    except (UsageError, I2CFault) as exc:
        return str(exc)
    return None


def _confirm(motors: MotorsConfig) -> str | None:
    """None when the board is off and nobody owns it, else what is wrong."""
    device = bus_device(motors.i2c_bus, motors.emulator)
    deadline = time.monotonic() + CONFIRM_S
    while owned(device) and time.monotonic() < deadline:
        time.sleep(0.02)
    still_owned = owned(device)
    owners = owner_pids(device)
    try:
        with I2CBus.for_motors(motors) as bus:
            if not read_mode1(bus, motors.address) & MODE1_SLEEP:
                stop_and_sleep(bus, motors.address)  # again; someone set the chip up
                return f"the board was set up again by {describe(owners)}"
    except (UsageError, I2CFault) as exc:
        return f"cannot read the board back: {exc}"
    if still_owned:
        return (f"{describe(owners)} still owns the bus {CONFIRM_S:g} s later (the chip "
                "sleeps, its outputs off; that process did not end)")
    return None


def _listed(items: list[str]) -> str:
    more = len(items) - MAX_NAMED
    return "; ".join(items[:MAX_NAMED]) + (f"; and {more} more" if more > 0 else "")


def run(args: argparse.Namespace) -> int:
    # This is systemd's ExecStopPost: a config edited while the service ran must not stop
    # the stop. The board the runtime recorded, else the defaults; and say so.
    motors, config_error = _motors(args.config)
    exit_code = 0 if config_error is None else EXIT_USAGE
    if args.board_emulator:  # the harness's board, whatever the config says or failed to say
        motors = dataclasses.replace(motors, emulator=args.board_emulator)
    if motors.emulator:
        print(f"jetbot-rt stop: {emulator_notice(motors.emulator)}", flush=True)
    where = f"I2C bus {motors.i2c_bus} address 0x{motors.address:02x}"
    error = _write_stop(motors, stop_and_sleep)  # first: nothing and nobody may delay it
    reply = request_stop()  # bounded in all: ASK_TOTAL_S
    if error is not None:  # a burst of bus errors: the asking gave the bus time to recover
        error = _write_stop(motors, stop_and_sleep)
    if reply:
        print("jetbot-rt stop: the running runtime latched its safe stop")
    if config_error is not None:
        print(f"jetbot-rt stop: {config_error}", file=sys.stderr)
    if reply.ignored:
        # another user's directory or socket, a link, or more than asked at most: never used
        print(f"jetbot-rt stop: ignored: {_listed(reply.ignored)}", file=sys.stderr)
    if error is None:
        error = _confirm(motors)
    if error is not None:
        print(f"jetbot-rt stop: motors NOT confirmed off ({where}): {error}", file=sys.stderr)
        return EXIT_BOARD_UNREACHABLE
    print(f"jetbot-rt stop: motor outputs off ({where}); the chip sleeps until a runtime "
          "sets it up again")
    if reply.unreachable:
        # Informative only: the board is confirmed off and nobody owns it any more.
        print(f"jetbot-rt stop: note: could not ask {len(reply.unreachable)} runtime "
              f"socket(s) to stop: {_listed(reply.unreachable)}", file=sys.stderr)
    return exit_code
