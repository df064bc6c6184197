"""``jetbot-rt check``: a self-test for a newly assembled robot, one table row per part.

Motor board (does a PCA9685 answer at the address), camera (N frames at the expected size and
rate, measured fps and mean colour), policy (loads, what it expects), onnxruntime providers.
The motors move only with ``--spin``: a short low-duty pulse per wheel, then the hardware stop.
Exit 1 if any row fails.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from jetbot_rt.config.schema import set_value
from jetbot_rt.config.sections import Config, load_config
from jetbot_rt.errors import UsageError, first_line
from jetbot_rt.hal.base import DEFAULT_FRAME_SIZE
from jetbot_rt.hal.i2c import EMULATOR_FLAG, add_emulator_argument
from jetbot_rt.service import signals

SPIN_DUTY = 0.3
SPIN_SECONDS = 0.5
MIN_RATE_FRACTION = 0.8  # measured fps below this share of [camera] fps fails the row


@dataclass
class Row:
    name: str
    ok: bool
    detail: str


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML config file")
    parser.add_argument("--policy", help="ONNX policy (default: [policy] path, else bundled)")
    parser.add_argument("--frames", type=int, default=30, help="camera frames to take")
    parser.add_argument(
        "--spin", action="store_true",
        help=f"pulse each wheel forward at duty {SPIN_DUTY} for {SPIN_SECONDS} s",
    )
    add_emulator_argument(parser)


def _row(name: str, probe: Callable[[], str]) -> Row:
    try:
        return Row(name, True, probe())
    except Exception as exc:  # a self-test reports every failure as a row, never a traceback
        return Row(name, False, first_line(exc))


def check_motor_board(config: Config) -> str:
    from jetbot_rt.hal.i2c import I2CBus, emulator_notice
    from jetbot_rt.hal.motors import read_mode1
    from jetbot_rt.hal.pca9685 import OSCILLATOR_HZ, PRE_SCALE

    motors = config.motors
    with I2CBus.for_motors(motors) as bus:
        mode1 = read_mode1(bus, motors.address)
        prescale = bytearray(1)
        bus.writeto_then_readfrom(motors.address, bytes((PRE_SCALE,)), prescale)
    pwm_hz = OSCILLATOR_HZ / 4096 / (prescale[0] + 1)
    emulated = f"; {emulator_notice(motors.emulator)}" if motors.emulator else ""
    return (
        f"PCA9685 answers on I2C bus {motors.i2c_bus} at 0x{motors.address:02x} "
        f"(MODE1 0x{mode1:02x}, PWM {pwm_hz:.0f} Hz); layout {motors.layout}{emulated}"
    )


def spin_wheels(config: Config) -> str:
    from jetbot_rt.hal.motors import open_drive

    # Every signal that would end or suspend the process raises ``Interrupted`` here (the
    # CLI's handler): the pulse ends in the finally below; a second signal cannot cut the
    # stop short (deferred), it is raised once the board is off.
    signals.raise_if_swallowed()  # a signal lost during the imports: no pulse
    drive = open_drive(config.motors)
    try:
        left_sign, right_sign = config.actions.sign  # forward as the runtime drives it
        for left, right in ((SPIN_DUTY * left_sign, 0.0), (0.0, SPIN_DUTY * right_sign)):
            drive.write(left, right)
            time.sleep(SPIN_SECONDS)
            drive.write(0.0, 0.0)
            time.sleep(0.2)
    finally:
        with signals.deferred():
            drive.stop()
            drive.close()
    return (f"left, then right wheel forward (sign {list(config.actions.sign)}) at duty "
            f"{SPIN_DUTY} for {SPIN_SECONDS} s; all off")


def check_camera(config: Config, size: tuple[int, int], frames: int) -> str:
    from jetbot_rt.hal.gst_camera import GstCamera

    camera = GstCamera(config.camera, size)
    camera.start()
    try:
        taken: list[Any] = []
        deadline = time.monotonic() + 2.0 + 2.0 * frames / config.camera.fps
        last_index = -1
        while len(taken) < frames and time.monotonic() < deadline:
            frame = camera.read()
            if frame is not None and frame.index != last_index:
                taken.append(frame)
                last_index = frame.index
            time.sleep(0.002)
    finally:
        camera.stop()
    if len(taken) < frames:
        raise RuntimeError(_short_of_frames(taken, frames, config.camera.fps))
    shape = taken[-1].image.shape
    if shape != (size[1], size[0], 3):
        raise RuntimeError(f"frames are {shape}, expected {(size[1], size[0], 3)}")
    span = taken[-1].t_capture - taken[0].t_capture
    fps = (len(taken) - 1) / span if span > 0 else float("inf")
    mean = taken[-1].image.reshape(-1, 3).mean(axis=0)
    detail = (
        f"{frames} frames {size[0]}x{size[1]} RGB at {fps:.1f} fps; "
        f"mean colour R {mean[0]:.0f} G {mean[1]:.0f} B {mean[2]:.0f}"
    )
    if fps < MIN_RATE_FRACTION * config.camera.fps:
        raise RuntimeError(f"{detail}: slower than {config.camera.fps:g} fps")
    return detail


def _short_of_frames(taken: list[Any], frames: int, expected_fps: float) -> str:
    """Why fewer than ``frames`` came in time: a camera that stopped delivering (stalled), or
    one that delivers, only slower than ``[camera] fps`` says."""
    now = time.monotonic()
    quiet = now - taken[-1].t_capture if taken else None
    if len(taken) >= 2:
        fps = (len(taken) - 1) / max(taken[-1].t_capture - taken[0].t_capture, 1e-9)
        if quiet is not None and quiet < max(1.0, 3.0 / fps):
            return (f"only {len(taken)} of {frames} frames in time: the camera delivers "
                    f"{fps:.1f} fps, slower than [camera] fps {expected_fps:g}")
    if not taken:
        return f"no frame arrived (expected {frames} at [camera] fps {expected_fps:g})"
    return (f"only {len(taken)} of {frames} frames arrived, then the camera stalled "
            f"(none for {quiet:.1f} s)")


def describe_policy(description: dict[str, Any]) -> str:
    width, height = description["size"]
    clip = description["clip"]
    clipped = "" if clip is None else f" clip {clip:g}"
    return (
        f"{description['path']}: input {description['input']} {description['layout']} "
        f"{width}x{height} {description['dtype']} {description['color_order']} "
        f"{description['pixel_range']}{clipped}; action output {description['action_output']}; "
        f"max_speed {description['run_max_speed']:g} ({description['max_speed_from']}); "
        f"running on {', '.join(description['providers'])}"
    )


def run_max_speed(configured: float | None, from_model: float | None) -> tuple[float, str]:
    """The max_speed ``jetbot-rt run`` with this config and policy drives at, and where it
    comes from (the same rule: ``actions.resolve_max_speed``)."""
    from jetbot_rt.runtime.actions import resolve_max_speed

    value = resolve_max_speed(configured, from_model)
    if configured is not None:
        return value, "[actions] max_speed"
    if value == from_model:
        return value, "the model's metadata"
    return value, "the default; set [actions] max_speed"


def check_providers() -> str:
    import onnxruntime as ort

    return f"onnxruntime {ort.__version__}: {', '.join(ort.get_available_providers())}"


def print_table(rows: list[Row]) -> None:
    width = max(len(row.name) for row in rows)
    for row in rows:
        print(f"{row.name:<{width}}  {'ok  ' if row.ok else 'FAIL'}  {row.detail}")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.board_emulator is not None:
        try:
            set_value(config.motors, "motors", "emulator", args.board_emulator)
        except UsageError as exc:
            raise UsageError(f"{EMULATOR_FLAG}: {exc}") from None
    config.validate()
    if args.policy == "":
        raise UsageError("--policy must be a file name, not empty")
    if args.frames < 2:
        raise UsageError(f"--frames must be at least 2, got {args.frames}")
    if args.spin:
        from jetbot_rt.hal.ownership import BoardLock

        # The wheels move only if this process owns the bus: refused (exit 2, naming the
        # owner) while a runtime drives, whatever its environment or user.
        owner = BoardLock.acquire(config.motors.i2c_bus, config.motors.emulator)
    rows = [_row("motor board", lambda: check_motor_board(config))]
    if args.spin:
        rows.append(_row("spin", lambda: spin_wheels(config)))
        owner.release()  # the wheels are done: a stop need not wait for the camera rows

    size = DEFAULT_FRAME_SIZE
    described: dict[str, Any] = {}

    def load_policy() -> str:
        from jetbot_rt.runtime.policy import OnnxPolicy, resolve_policy_path

        path = resolve_policy_path(args.policy or config.policy.path)
        policy = OnnxPolicy.load(path, config.policy)
        described.update(policy.describe())
        described["run_max_speed"], described["max_speed_from"] = run_max_speed(
            config.actions.max_speed, policy.max_speed)
        return describe_policy(described)

    policy_row = _row("policy", load_policy)
    if described:
        size = (described["size"][0], described["size"][1])
    rows.append(_row("camera", lambda: check_camera(config, size, args.frames)))
    rows.append(policy_row)
    rows.append(_row("providers", check_providers))
    print_table(rows)
    return 0 if all(row.ok for row in rows) else 1
