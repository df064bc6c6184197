"""``jetbot-rt stop``: turn every motor output off, latch a running runtime's safe stop, report.

This is what systemd runs after every end of the service (``ExecStopPost``), a crash or a
watchdog kill included, so it needs nothing but the config and the I2C bus: no camera, no
policy, no onnxruntime. The hardware stop is written first, whatever else fails: on the
configured bus and address if the config can be read (in bounded time), else on the defaults.
Exit 0 when the motors are off; 1 when the board cannot be reached or a running runtime could
not be told to stop; 2 when the config is bad (the stop is still written, on the default bus
and address).
"""

from __future__ import annotations

import argparse
import sys

from jetbot_rt.config import MotorsConfig, load_config
from jetbot_rt.control import request_stop
from jetbot_rt.errors import EXIT_USAGE, UsageError, first_line
from jetbot_rt.hal.i2c import I2CBus, I2CFault
from jetbot_rt.hal.motors import hardware_stop

EXIT_BOARD_UNREACHABLE = 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML config file (for [motors] bus and address)")


def _motors(path: str | None) -> tuple[MotorsConfig, str | None]:
    """The config's [motors], or the defaults and why; never raises."""
    try:
        return load_config(path).motors, None
    except UsageError as exc:
        return MotorsConfig(), str(exc)
    except Exception as exc:  # the stop must go out whatever the config holds
        return MotorsConfig(), f"config {path}: {type(exc).__name__}: {first_line(exc)}"


def _write_stop(motors: MotorsConfig) -> str | None:
    """The hardware stop; None when written, else why not."""
    try:
        with I2CBus.open(motors.i2c_bus, motors.i2c_retries, motors.address) as bus:
            hardware_stop(bus, motors.address)
    except (UsageError, I2CFault) as exc:
        return str(exc)
    return None


def run(args: argparse.Namespace) -> int:
    motors, config_error = _motors(args.config)
    exit_code = 0
    if config_error is not None:
        # This is systemd's ExecStopPost: a config edited while the service ran must not
        # stop the stop. Fall back to the default bus and address, and say so.
        motors = MotorsConfig()
        exit_code = EXIT_USAGE
    where = f"I2C bus {motors.i2c_bus} address 0x{motors.address:02x}"
    error = _write_stop(motors)  # first: nothing below may delay it
    reply = request_stop()
    if reply:
        print("jetbot-rt stop: the running runtime latched its safe stop")
        error = _write_stop(motors)  # again, after the runtime's last tick
    if config_error is not None:
        print(f"jetbot-rt stop: {config_error}; using the default bus and address",
              file=sys.stderr)
    if error is not None:
        print(f"jetbot-rt stop: motors NOT confirmed off ({where}): {error}", file=sys.stderr)
        return EXIT_BOARD_UNREACHABLE
    print(f"jetbot-rt stop: motor outputs off ({where})")
    for problem in reply.unreachable:
        # A runtime we could not reach would overwrite the stop at its next tick.
        print(f"jetbot-rt stop: a runtime may still be driving, its control socket "
              f"{problem} (run as the service user or root)", file=sys.stderr)
        exit_code = EXIT_BOARD_UNREACHABLE
    return exit_code
