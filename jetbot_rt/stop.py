"""``jetbot-rt stop``: latch a running runtime's safe stop, then turn every motor output off.

This is what systemd runs after every end of the service (``ExecStopPost``), a crash or a
watchdog kill included, so it needs nothing but the config and the I2C bus: no camera, no
policy, no onnxruntime. Exit 0 when the motors are off; 1 when the board cannot be reached
or a running runtime could not be told to stop; 2 when the config is bad (the stop is still
written, on the default bus and address).
"""

from __future__ import annotations

import argparse
import sys

from jetbot_rt.config import MotorsConfig, load_config
from jetbot_rt.control import request_stop
from jetbot_rt.errors import EXIT_USAGE, UsageError
from jetbot_rt.hal.i2c import I2CBus, I2CFault
from jetbot_rt.hal.motors import hardware_stop

EXIT_BOARD_UNREACHABLE = 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML config file (for [motors] bus and address)")


def run(args: argparse.Namespace) -> int:
    # The runtime first: it needs no config, and a bad config must not keep it driving.
    reply = request_stop()
    if reply:
        print("jetbot-rt stop: the running runtime latched its safe stop")
    exit_code = 0
    try:
        motors = load_config(args.config).motors
    except UsageError as exc:
        # This is systemd's ExecStopPost: a config edited while the service ran must not
        # stop the stop. Fall back to the default bus and address, and say so.
        print(f"jetbot-rt stop: {exc}; using the default bus and address", file=sys.stderr)
        motors = MotorsConfig()
        exit_code = EXIT_USAGE
    where = f"I2C bus {motors.i2c_bus} address 0x{motors.address:02x}"
    try:
        with I2CBus.open(motors.i2c_bus, motors.i2c_retries, motors.address) as bus:
            hardware_stop(bus, motors.address)
    except (UsageError, I2CFault) as exc:
        print(f"jetbot-rt stop: motors NOT confirmed off ({where}): {exc}", file=sys.stderr)
        return EXIT_BOARD_UNREACHABLE
    print(f"jetbot-rt stop: motor outputs off ({where})")
    for problem in reply.unreachable:
        # A runtime we could not reach would overwrite the stop at its next tick.
        print(f"jetbot-rt stop: a runtime may still be driving, its control socket "
              f"{problem} (run as the service user or root)", file=sys.stderr)
        exit_code = EXIT_BOARD_UNREACHABLE
    return exit_code
