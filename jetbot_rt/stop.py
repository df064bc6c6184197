"""``jetbot-rt stop``: latch a running runtime's safe stop, then turn every motor output off.

This is what systemd runs after every end of the service (``ExecStopPost``), a crash or a
watchdog kill included, so it needs nothing but the config and the I2C bus: no camera, no
policy, no onnxruntime. Exit 0 when the motors are off, 1 when the board cannot be reached.
"""

from __future__ import annotations

import argparse
import sys

from jetbot_rt.config import load_config
from jetbot_rt.control import request_stop
from jetbot_rt.errors import UsageError
from jetbot_rt.hal.i2c import I2CBus, I2CFault
from jetbot_rt.hal.motors import hardware_stop

EXIT_BOARD_UNREACHABLE = 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML config file (for [motors] bus and address)")


def run(args: argparse.Namespace) -> int:
    motors = load_config(args.config).motors
    if request_stop():
        print("jetbot-rt stop: the running runtime latched its safe stop")
    where = f"I2C bus {motors.i2c_bus} address 0x{motors.address:02x}"
    try:
        with I2CBus.open(motors.i2c_bus, motors.i2c_retries, motors.address) as bus:
            hardware_stop(bus, motors.address)
    except (UsageError, I2CFault) as exc:
        print(f"jetbot-rt stop: motors NOT confirmed off ({where}): {exc}", file=sys.stderr)
        return EXIT_BOARD_UNREACHABLE
    print(f"jetbot-rt stop: motor outputs off ({where})")
    return 0
