"""``jetbot-rt calibrate``: measure the robot with its own camera and write the ``[sim]`` keys
that make the simulator drive like it (docs/CALIBRATION.md).

The drive is ``jetbot-rt run``'s: the same phases (control socket, the board's single owner,
the latch, the watchdog, the signals, the recorder, exit codes), with the drive programme
(``calibration.programme``) in the policy's place and the marker watched on every frame. Then
the fit (``calibration.fit``) reads the recording back; ``--fit RECORDING`` does only that.

``--camera`` measures the lens instead (``calibration.intrinsics``): a printed checkerboard's
views from the camera (the motors are never opened) or from ``--frames DIR``, fitted by
OpenCV's fisheye model, written as the ``[sim]`` lens keys.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

from jetbot_rt.calibration.fit import Data, fit, to_toml
from jetbot_rt.calibration.intrinsics import MIN_VIEWS, board_png, calibrate
from jetbot_rt.calibration.intrinsics import to_toml as intrinsics_toml
from jetbot_rt.calibration.measure import Geometry, MarkerMeter, marker_png
from jetbot_rt.calibration.programme import Limits, Programme, duration
from jetbot_rt.calibration.views import board_views, collect, enough, load_frames, save_frames
from jetbot_rt.commands.lifecycle import Phase
from jetbot_rt.commands.run import Runtime
from jetbot_rt.commands.run_phases import Connect, Drive, Load
from jetbot_rt.config import safe_file
from jetbot_rt.config.sections import Config, load_config
from jetbot_rt.errors import EXIT_OK, UsageError
from jetbot_rt.hal.i2c import add_emulator_argument
from jetbot_rt.hal.registry import BACKEND_MODULES
from jetbot_rt.recording.reader import Recording
from jetbot_rt.recording.recorder import expand_path
from jetbot_rt.sim.config import SimConfig

FRAME_SIZE = (320, 180)
SIM_MARKER_DISTANCE = 0.5
DONE = "calibration programme done"
CAMERA_FRAME_SIZE = {"real": (1280, 720), "sim": (640, 360)}
"""The lens is measured at the camera's full capture (real) and at a size the sim renders
in a blink; the keys are normalised by the frame's size, so they hold at any size."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backend", choices=sorted(BACKEND_MODULES),
                        help="sim or real: drive the programme and fit (not with --fit)")
    parser.add_argument("--fit", metavar="RECORDING",
                        help="fit a calibration recording again, without driving")
    parser.add_argument("--config", help="TOML config file ([loop], [motors], [actions] sign; "
                        "in the sim, [sim] is the robot to measure)")
    parser.add_argument("--out", help="write the [sim] table to this file (default: print it)")
    parser.add_argument("--record", metavar="DIR", default="calibration-{time}",
                        help="the recording of the drive (default: calibration-{time})")
    parser.add_argument("--yes", action="store_true", help="do not ask to clear the area")
    parser.add_argument("--max-duty", type=float, default=Limits.max_duty,
                        help=f"largest duty of any step, in (0, 0.6] (default {Limits.max_duty})")
    parser.add_argument("--max-travel", type=float, default=Limits.max_travel,
                        help="stop when the marker's range changes by more than this many m "
                             f"(default {Limits.max_travel})")
    parser.add_argument("--marker-size", type=float, default=Geometry.marker_size,
                        help=f"the printed marker's black square, m (default "
                             f"{Geometry.marker_size})")
    parser.add_argument("--marker-height", type=float,
                        help="its centre above the floor, m (default: 2/3 of --marker-size, "
                             "the page standing on the floor)")
    parser.add_argument("--wheel-radius", type=float, default=Geometry.wheel_radius)
    parser.add_argument("--track", type=float, default=Geometry.track,
                        help="distance between the wheels' centres, m")
    parser.add_argument("--camera-offset", type=float, default=Geometry.camera_offset,
                        help="camera ahead of the wheel axle, m")
    parser.add_argument("--camera", action="store_true",
                        help="measure the lens instead: a printed checkerboard "
                             f"({board_png().name}) in front of the camera, or --frames")
    parser.add_argument("--frames", metavar="DIR",
                        help="--camera: fit the board's views in these images (png, jpg)")
    parser.add_argument("--views", type=int, default=15,
                        help="--camera: views of the board to take (default 15)")
    parser.add_argument("--time-limit", type=float, default=180.0,
                        help="--camera: give up taking views after this many s (default 180)")
    add_emulator_argument(parser)


def _geometry(args: argparse.Namespace, sim: SimConfig) -> Geometry:
    checks = [("--marker-size", args.marker_size, 0.01, 1.0),
              ("--wheel-radius", args.wheel_radius, 0.005, 0.5),
              ("--track", args.track, 0.02, 1.0), ("--camera-offset", args.camera_offset, -0.5,
                                                    0.5)]
    height = args.marker_height if args.marker_height is not None else args.marker_size * 2 / 3
    checks.append(("--marker-height", height, 0.0, 2.0))
    for flag, value, low, high in checks:
        if not (math.isfinite(value) and low <= value <= high):
            raise UsageError(f"{flag} must be in [{low:g}, {high:g}], got {value:g}")
    lens = {}
    if sim.lens == "fisheye":  # the marker is measured through the configured lens
        lens = {"lens_focal": sim.lens_focal, "lens_cx": sim.lens_center[0],
                "lens_cy": sim.lens_center[1], "lens_k1": sim.lens_k1, "lens_k2": sim.lens_k2,
                "lens_k3": sim.lens_k3, "lens_k4": sim.lens_k4}
    return Geometry(marker_size=args.marker_size, marker_height=height,
                    camera_height=sim.camera_height, camera_offset=args.camera_offset,
                    wheel_radius=args.wheel_radius, track=args.track,
                    vfov_deg=sim.camera_vfov_deg, **lens)


class LoadProgramme(Phase):
    """In ``Load``'s place: the programme is the policy."""

    def __init__(self, programme: Programme) -> None:
        self.policy = programme

    def enter(self) -> None:
        """Nothing to load."""


class PlaceMarker(Phase):
    """Sim only: the printed page in front of the robot, and the world run until the robot
    has settled and the camera's latency queue shows the page."""

    def __init__(self, rt: Calibration, connect: Connect) -> None:
        self.rt = rt
        self.connect = connect

    def enter(self) -> None:
        if self.rt.args.backend != "sim":
            return
        from jetbot_rt.sim.fiducial import place_marker

        robot, _ = self.connect.connected
        geometry = self.rt.programme.geometry
        place_marker(robot, SIM_MARKER_DISTANCE, geometry.marker_size,  # type: ignore[arg-type]
                     geometry.marker_height)
        robot.step(0.5)


class Arm(Phase):
    def __init__(self, rt: Calibration, connect: Connect) -> None:
        self.rt = rt
        self.connect = connect

    def enter(self) -> None:
        robot, _ = self.connect.connected
        latch = self.rt.latch
        self.rt.programme.arm(robot.simulated, lambda: latch.trip(DONE, fault=False))


class Calibration(Runtime):
    """``jetbot-rt run`` with the programme for a policy."""

    def __init__(self, args: argparse.Namespace, limits: Limits) -> None:
        for name in ("policy", "max_speed", "telemetry", "rate"):
            setattr(args, name, None)
        args.gui = False
        args.duration = None  # the programme ends the drive (``Arm``)
        args.record = str(expand_path(args.record))  # known here: the fit reads it back
        super().__init__(args)
        self.config.actions.max_speed = 1.0  # the programme's duties are the duties
        self.config.actions.trim = [1.0, 1.0]  # the robot as it is, untrimmed
        self.config.actions.deadband = 0.0  # unlifted: the dead-band is what it measures
        sim = self.config.sim
        geometry = _geometry(args, sim)
        self.programme = Programme(geometry, limits, FRAME_SIZE, self.config.loop.rate_hz)

    def phases(self) -> list[Phase]:
        """``run``'s phases with the programme in ``Load``'s place (every phase that reads
        the policy is given it), the page placed once connected (sim), armed before the drive."""
        load = LoadProgramme(self.programme)
        phases: list[Phase] = []
        connect: Connect | None = None
        for phase in super().phases():
            if hasattr(phase, "load"):
                phase.load = load  # type: ignore[attr-defined]
            if isinstance(phase, Load):
                phase = load
            if isinstance(phase, Drive) and connect is not None:
                phases.append(Arm(self, connect))
            phases.append(phase)
            if isinstance(phase, Connect):
                connect = phase
                phases.append(PlaceMarker(self, connect))
        return phases


def _limits(args: argparse.Namespace) -> Limits:
    if not (math.isfinite(args.max_duty) and 0 < args.max_duty <= 0.6):
        raise UsageError(f"--max-duty must be in (0, 0.6], got {args.max_duty:g}")
    if not (math.isfinite(args.max_travel) and 0.02 <= args.max_travel <= 2.0):
        raise UsageError(f"--max-travel must be in [0.02, 2] m, got {args.max_travel:g}")
    return Limits(max_duty=args.max_duty, max_travel=args.max_travel)


def read_data(path: str) -> tuple[Data, Geometry, float]:
    """The ticks of a calibration recording: when each duty was written, the duties, and
    what each frame showed."""
    recording = Recording.open(path)
    described = recording.meta.get("policy", {})
    if not isinstance(described, dict) or described.get("programme") != "calibrate":
        raise UsageError(f"{path} is not a calibration recording (jetbot-rt calibrate --record)")
    try:
        geometry = Geometry(**{k: float(v) for k, v in described["geometry"].items()})
        max_duty = float(described["limits"]["max_duty"])
        width, height = (int(v) for v in recording.meta["frame_size"])
        period = 1.0 / float(recording.meta["rate_hz"])
        if not all(math.isfinite(v) and (v >= 0 or k.startswith("lens_k"))
                   for k, v in vars(geometry).items()) or not (
                0 < max_duty <= 1 and 0 < period < 1 and width > 0 and height > 0):
            raise ValueError("a value out of range")
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise UsageError(f"{path}: meta.json's calibration is unreadable ({exc})") from None
    meter = MarkerMeter(geometry, (width, height))
    simulated = recording.meta.get("backend") == "sim"
    rows: list[list[float]] = []
    for record, image in recording.ticks_with_frames():
        try:
            # the sim's time is one period per tick (a late tick there loses no time)
            t = (int(record["tick"]) - 1) * period if simulated else float(record["t"])
            left, right = (float(v) for v in record["cmd"])
        except (KeyError, TypeError, ValueError) as exc:
            raise UsageError(f"{path}: a tick record without its time or duties ({exc})") \
                from None
        seen = meter.measure(image) if image is not None else None
        rows.append([t, left, right, *(seen if seen is not None else (math.nan, math.nan))])
    if len(rows) < 30:
        raise UsageError(f"{path}: {len(rows)} ticks recorded; too few to fit")
    table = np.array(rows)
    return Data(table[:, 0], table[:, 1:3], table[:, 3], table[:, 4]), geometry, max_duty


def fit_recording(path: str, out: str | None) -> int:
    data, geometry, max_duty = read_data(path)
    try:
        result = fit(data, geometry, max_duty)
    except ValueError as exc:
        raise UsageError(f"{path}: {exc}") from None
    return write_toml(to_toml(result, geometry, comment_text(path)), out)


def comment_text(path: str) -> str:
    """``path`` as the output's first comment line shows it: a byte that is not UTF-8 as
    ``\\xNN`` (a lone surrogate cannot be encoded or printed) and a line break or other
    control character escaped, since a path may hold one and it would start a TOML line of
    its own in the file ``--out`` writes (``--frames 'v\\n[sim]\\nmotor_gain = 9'``)."""
    return "".join(c if c.isprintable() else ascii(c)[1:-1] for c in safe_file.shown(path))


def write_toml(text: str, out: str | None) -> int:
    """``text`` into ``out`` (replaced whole, or not at all), else on stdout."""
    if out:
        target = Path(out)
        try:
            with safe_file.replaced_file(target.parent, target.name) as fd:
                os.write(fd, text.encode())
        except OSError as exc:
            raise UsageError(f"cannot write {out}: {exc.strerror or exc}") from None
        print(f"wrote {out}")
    else:
        print(text, end="")
    return EXIT_OK


def camera_views(args: argparse.Namespace) -> tuple[list[np.ndarray], tuple[int, int], str]:
    """The board's corners in each view, the frames' size and where they came from: the
    images of ``--frames``, or the camera's (the views then saved under ``--record``)."""
    if args.frames:
        if args.backend:
            raise UsageError("--camera --frames reads images; it takes no --backend")
        images = load_frames(args.frames)
        height, width = images[0].shape[:2]
        views = board_views(images)
        enough(views, len(images), args.frames)
        return views, (width, height), args.frames
    if not args.backend:
        raise UsageError("--camera: give --backend (sim or real) to take views, or --frames DIR")
    if not MIN_VIEWS <= args.views <= 200 or not (math.isfinite(args.time_limit)
                                                  and 1 <= args.time_limit <= 3600):
        raise UsageError(f"--views must be in [{MIN_VIEWS}, 200] and --time-limit in "
                         "[1, 3600] s")
    config = load_config(args.config)
    size = CAMERA_FRAME_SIZE.get(args.backend, CAMERA_FRAME_SIZE["real"])
    if args.backend == "sim":
        from jetbot_rt.sim.board import sim_views

        images = sim_views(config.sim, size, args.views)
    else:
        images = live_views(args, config, size)
    views = board_views(images)
    enough(views, len(images), f"--backend {args.backend}")
    record = Path(str(expand_path(args.record)))
    save_frames(record, images)
    print(f"saved the views in {record} (--camera --frames {record} fits them again)")
    return views, size, str(record)


def live_views(args: argparse.Namespace, config: Config, size: tuple[int, int]) -> list:
    """The camera's frames with the board in view; the motors are never opened."""
    from jetbot_rt.hal.registry import BackendOptions, make_backend

    robot = make_backend(args.backend, config, BackendOptions(frame_size=size))
    last: list[int] = [-1]

    def read() -> np.ndarray | None:
        frame = robot.camera.read()
        if frame is None or frame.index == last[0]:
            return None
        last[0] = frame.index
        return frame.image

    print(f"hold the board ({board_png()}, printed flat) 0.2-0.6 m in front of the camera, "
          "the whole board in view; move and tilt it between views", flush=True)
    robot.camera.start()
    try:
        return collect(read, args.views, args.time_limit, size, print)
    finally:
        robot.camera.stop()


def camera_run(args: argparse.Namespace) -> int:
    if args.fit:
        raise UsageError("--camera measures the lens; --fit re-fits a drive's recording")
    views, size, source = camera_views(args)
    try:
        result = calibrate(views, size)
    except ValueError as exc:
        raise UsageError(f"{source}: {exc}") from None
    return write_toml(intrinsics_toml(result, comment_text(source)), args.out)


def run(args: argparse.Namespace) -> int:
    if args.camera:
        return camera_run(args)
    if args.fit:
        if args.backend:
            raise UsageError("--fit reads a recording; it takes no --backend")
        return fit_recording(args.fit, args.out)
    if not args.backend:
        raise UsageError("give --backend (sim or real) to drive, or --fit RECORDING")
    limits = _limits(args)
    calibration = Calibration(args, limits)
    if not args.yes:
        print(f"jetbot-rt calibrate drives for {duration(limits.max_duty):.0f} s at duties up "
              f"to {limits.max_duty:g} and stops if the marker's range changes by "
              f"{limits.max_travel:g} m. Print {marker_png()} with its black square "
              f"{args.marker_size * 100:g} cm wide, stand it ~0.5 m ahead of the camera, clear "
              "the area. Enter to start, Ctrl-C to cancel: ", end="", flush=True)
        if sys.stdin.readline() == "":
            raise UsageError("no answer on stdin (use --yes)")
    result = calibration.run()
    if result.reason != DONE:  # a fault, a signal, `jetbot-rt stop`: the programme is cut
        if result.exit_code == EXIT_OK:
            print(f"jetbot-rt calibrate: not fitted: the programme did not finish "
                  f"({result.reason}); the recording is {calibration.config.record.path}",
                  file=sys.stderr)
        return result.exit_code
    return fit_recording(str(calibration.config.record.path), args.out)
