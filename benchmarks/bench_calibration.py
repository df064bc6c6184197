"""The drive calibration's proof and the measurements behind it (docs/CALIBRATION.md):

- drive: ``jetbot-rt calibrate --backend sim --config TRUTH --yes`` for each truth, through
  the pinhole and the default (datasheet) fisheye, and the sixth truth through a wider,
  barrel fisheye too; the fitted values against the truth's; how far the programme moved
  the robot; each recording fitted again without the rest frames' extra weight;
- marker: the marker's range and bearing as measured in one frame against the simulator's
  geometry, 0.5 m ahead of the axle, at bearings -30..30 degrees, through each lens;
- kinematics: PyBullet's robot against ideal differential-drive kinematics on the motor
  model's wheel speeds (one wheel driven, the other braked; on the spot; straight), over one
  programme step and with the duty held;
- lens: ``calibrate``'s lens fit on exact synthetic corners (the sim's board views,
  re-projected through the true lens): OpenCV's ``cv2.fisheye.calibrate`` alone, then with
  the refinement, for the five truths of bench_lens_recovery.py.

    python benchmarks/bench_calibration.py [--out benchmarks/results] [--only drive,...]

Writes calibration.json and calibration.md to --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tomllib
from bench_lens_recovery import TRUTHS as LENS_TRUTHS
from bench_sim import machine
from versions import run_record, write_results

from jetbot_rt.calibration import fit as fit_module
from jetbot_rt.calibration.intrinsics import (
    FISHEYE_FLAGS_4X,
    SENSOR_ASPECT,
    Lens,
    board_points,
    calibrate,
    fisheye_flags,
    radial_error_px,
)
from jetbot_rt.calibration.measure import Geometry, MarkerMeter
from jetbot_rt.calibration.views import board_views
from jetbot_rt.commands import calibrate as calibrate_command
from jetbot_rt.config.sections import Config, load_config
from jetbot_rt.hal.registry import BackendOptions
from jetbot_rt.sim.backend import SimRobot, build_backend, scene_task
from jetbot_rt.sim.board import sim_views
from jetbot_rt.sim.fiducial import place_marker
from jetbot_rt.sim.motor import WheelMotors
from jetbot_rt.tasks.loader import load_task

TRUTHS: list[dict[str, Any]] = [
    {"motor_gain": 20.0, "wheel_gain": [1.0, 1.0], "deadband": 0.0, "latency": 0.0},
    {"motor_gain": 20.0, "wheel_gain": [0.75, 1.0], "deadband": 0.12, "latency": 0.05,
     "camera_latency": 0.05},
    {"motor_gain": 15.0, "wheel_gain": [1.0, 0.85], "deadband": 0.05, "latency": 0.15},
    {"motor_gain": 15.0, "wheel_gain": [1.0, 0.85], "deadband": 0.05, "latency": 0.0},
    {"motor_gain": 15.0, "wheel_gain": [1.0, 1.0], "deadband": 0.05, "latency": 0.15},
    {"motor_gain": 20.0, "wheel_gain": [1.0, 0.8], "deadband": 0.08, "latency": 0.15},
    {"motor_gain": 25.0, "wheel_gain": [0.9, 1.0], "deadband": 0.15, "latency": 0.05},
]
"""The drive's truths (docs/CALIBRATION.md's table, in its order); motor_tau is the sim's
default 0.05 s in all."""
LENSES: dict[str, dict[str, Any]] = {
    "pinhole": {"lens": "pinhole"},
    "datasheet fisheye": {"lens": "fisheye"},
    "wide barrel fisheye": {"lens": "fisheye", "lens_focal": 0.95, "lens_k1": 0.05,
                            "lens_k2": -0.02},
}
"""What the marker is seen through: the pinhole of ``camera_vfov_deg``, the sim's default
fisheye, and bench_lens_recovery's "wide, barrel" lens."""
DRIVES: list[tuple[int, str]] = [
    *((i, "pinhole") for i in range(len(TRUTHS))),
    *((i, "datasheet fisheye") for i in range(len(TRUTHS))),
    (5, "wide barrel fisheye"),
]
"""(truth index, lens) of each drive."""
TAU_TRUE = 0.05
FRAME_SIZE = calibrate_command.FRAME_SIZE
MARKER_DISTANCE = calibrate_command.SIM_MARKER_DISTANCE
BEARINGS_DEG = list(range(-30, 31, 5))


def toml_text(table: dict[str, Any]) -> str:
    return "[sim]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in table.items())


def sim_config(table: dict[str, Any], where: Path) -> Config:
    path = where / "sim.toml"
    path.write_text(toml_text(table))
    return load_config(str(path))


# -- the drive ------------------------------------------------------------------------------

def drive(index: int, lens: str, where: Path) -> dict[str, Any]:
    """One ``jetbot-rt calibrate`` through the command, then its recording fitted again in
    this process: with the rest frames weighted as the command does, and without."""
    truth = TRUTHS[index]
    (where / "truth.toml").write_text(toml_text({**truth, **LENSES[lens]}))
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "jetbot_rt.cli", "calibrate", "--backend",
                           "sim", "--config", "truth.toml", "--yes", "--record", "rec", "--out",
                           "fit.toml"], cwd=where, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        return {"truth": index + 1, "lens": lens, "exit_code": done.returncode,
                "stderr": done.stderr[-2000:]}
    written = tomllib.loads((where / "fit.toml").read_text())["sim"]
    data, geometry, max_duty = calibrate_command.read_data(str(where / "rec"))
    t1 = time.perf_counter()
    result = fit_module.fit(data, geometry, max_duty)
    fit_s = time.perf_counter() - t1
    v = result.values
    # the command's own output is this fit's (the same recording, the same code)
    assert abs(written["motor_gain"] - max(v["gain_left"], v["gain_right"])) < 1e-3, written
    saved = fit_module.REST_WEIGHT
    fit_module.REST_WEIGHT = 1.0
    try:
        unweighted = fit_module.fit(data, geometry, max_duty).values
    finally:
        fit_module.REST_WEIGHT = saved
    gains = [truth["motor_gain"] * w for w in truth["wheel_gain"]]
    latency = truth["latency"] + truth.get("camera_latency", 0.0)
    true_values = {"gain_left": gains[0], "gain_right": gains[1],
                   "deadband_left": truth["deadband"], "deadband_right": truth["deadband"],
                   "latency": latency}
    return {
        "truth": index + 1, "lens": lens, "exit_code": 0, "wall_s": round(wall, 1),
        "fit_s": round(fit_s, 2), "frames": result.frames,
        "true_gains": gains, "true_deadband": truth["deadband"], "true_latency": latency,
        "true_wheel_gain": truth["wheel_gain"],
        "gain": [round(v["gain_left"], 2), round(v["gain_right"], 2)],
        "gain_error_pct": [round(100 * (v[k] / g - 1), 1)
                           for k, g in zip(("gain_left", "gain_right"), gains, strict=True)],
        "motor_gain": written["motor_gain"],
        "motor_gain_error_pct": round(100 * (written["motor_gain"] / max(gains) - 1), 1),
        "wheel_gain": written["wheel_gain"],
        "wheel_gain_error": round(max(abs(a - b) for a, b in
                                      zip(written["wheel_gain"], truth["wheel_gain"],
                                          strict=True)), 4),
        "deadband_lr": [round(v["deadband_left"], 4), round(v["deadband_right"], 4)],
        "deadband": written["deadband"],
        "latency_ms": round(1e3 * v["latency"], 1),
        "latency_error_ms": round(1e3 * (v["latency"] - latency), 1),
        "tau_ms": round(1e3 * v["tau"], 1), "track_mm": round(1e3 * v["track"], 1),
        "rms_mm": round(result.rms_range_mm, 2), "rms_deg": round(result.rms_bearing_deg, 3),
        "unweighted_gain_error_pct": [
            round(100 * (unweighted[k] / g - 1), 1)
            for k, g in zip(("gain_left", "gain_right"), gains, strict=True)],
        "error_over_sigma": {key: round(abs(v[key] - want) / result.sigma[key], 1)
                             for key, want in true_values.items()},
        "moved": moved(where / "rec" / "ticks.jsonl"),
        "toml": (where / "fit.toml").read_text(),
    }


def moved(ticks: Path) -> dict[str, float]:
    """How far the programme took the robot from where it started (the sim's pose)."""
    records = [json.loads(line) for line in ticks.read_text().splitlines()]
    poses = np.array([r["pose"] for r in records if "tick" in r and "pose" in r])
    away = np.hypot(poses[:, 0] - poses[0, 0], poses[:, 1] - poses[0, 1])
    turned = np.abs(np.unwrap(poses[:, 2]) - poses[0, 2])
    return {"max_distance_cm": round(100 * float(away.max()), 1),
            "max_turn_deg": round(math.degrees(float(turned.max())), 1),
            "end_distance_cm": round(100 * float(away[-1]), 1),
            "end_turn_deg": round(math.degrees(float(turned[-1])), 1)}


# -- the marker -----------------------------------------------------------------------------

class _FacingAhead:
    """``place_marker``'s robot, with its heading replaced: the page is stood ahead of the
    axle on ``yaw``, whichever way the robot itself faces."""

    def __init__(self, robot: SimRobot, yaw: float) -> None:
        self._robot = robot
        self._yaw = yaw

    @property
    def world(self) -> _FacingAhead:
        return self

    @property
    def client(self) -> int:
        return self._robot.world.client

    def robot_pose(self) -> tuple[float, float, float]:
        x, y, _ = self._robot.world.robot_pose()
        return x, y, self._yaw

    def step(self, dt: float) -> None:
        self._robot.step(dt)


def camera_bearing(turn: float, offset: float = Geometry.camera_offset) -> float:
    """The bearing (rad, right positive) from a camera ``offset`` m ahead of the axle of a
    marker ahead of the axle's start, the robot turned ``turn`` rad (left positive) about its
    axle: planar geometry."""
    return turn - math.atan2(-offset * math.sin(turn), MARKER_DISTANCE - offset * math.cos(turn))


def turn_for(bearing_deg: float) -> float:
    """The turn that puts the marker at ``bearing_deg`` from the camera (Newton)."""
    target = turn = math.radians(bearing_deg)
    for _ in range(20):
        slope = (camera_bearing(turn + 1e-6) - camera_bearing(turn - 1e-6)) / 2e-6
        turn -= (camera_bearing(turn) - target) / slope
    return turn


def marker(lens: str, where: Path) -> dict[str, Any]:
    """The marker 0.5 m ahead of the axle's start, the robot turned about its axle so that
    the camera sees it at each of BEARINGS_DEG; what ``MarkerMeter`` measures in one frame
    against the truth from the simulator's camera pose."""
    config = sim_config(LENSES[lens], where)
    parser = argparse.ArgumentParser()
    calibrate_command.add_arguments(parser)
    geometry = calibrate_command._geometry(parser.parse_args([]), config.sim)
    options = BackendOptions(frame_size=FRAME_SIZE)
    robot = build_backend(config, options)
    assert isinstance(robot, SimRobot)
    scene = load_task(scene_task(config, options)).scene(
        np.random.default_rng(config.sim.seed), False)
    x0, y0, yaw0 = scene.robot_pose
    centre = np.array([x0 + MARKER_DISTANCE * math.cos(yaw0),
                       y0 + MARKER_DISTANCE * math.sin(yaw0)])
    meter = MarkerMeter(geometry, FRAME_SIZE)
    rows = []
    try:
        for bearing in BEARINGS_DEG:
            # turned left, the robot sees the page on its old heading to its right
            world = robot.world
            world.reset(scene=dataclasses.replace(
                scene, robot_pose=(x0, y0, yaw0 + turn_for(bearing))))
            place_marker(_FacingAhead(robot, yaw0), MARKER_DISTANCE,  # type: ignore[arg-type]
                         geometry.marker_size, geometry.marker_height)
            robot.step(0.5)  # settled, as the calibration's PlaceMarker
            eye, axes = world.camera_pose()
            ahead = centre - eye[:2]
            forward = axes[:2, 0] / np.linalg.norm(axes[:2, 0])
            right = -axes[:2, 1] / np.linalg.norm(axes[:2, 1])
            true_range = float(np.hypot(*ahead))
            true_bearing = math.degrees(math.atan2(ahead @ right, ahead @ forward))
            seen = meter.measure(world.frame())
            row: dict[str, Any] = {"bearing_deg": bearing, "true_range_m": round(true_range, 4),
                                   "true_bearing_deg": round(true_bearing, 3)}
            if seen is not None:
                row["range_error_mm"] = round(1e3 * (seen[0] - true_range), 2)
                row["bearing_error_deg"] = round(math.degrees(seen[1]) - true_bearing, 3)
            rows.append(row)
    finally:
        robot.disconnect()
    found = [r for r in rows if "range_error_mm" in r]
    summary: dict[str, Any] = {"lens": lens, "rows": rows, "found": len(found),
                               "of": len(rows)}
    for key in ("range_error_mm", "bearing_error_deg"):
        values = np.array([r[key] for r in found])
        summary[key] = {"mean": round(float(values.mean()), 3),
                        "sd": round(float(values.std()), 3),
                        "max_abs": round(float(np.abs(values).max()), 3),
                        "at_0": next(r[key] for r in found if r["bearing_deg"] == 0)}
    return summary


# -- the kinematics -------------------------------------------------------------------------

KINEMATICS = {
    "left wheel 0.1, right braked": (0.1, 0.0),
    "left wheel 0.3, right braked": (0.3, 0.0),
    "right wheel 0.3, left braked": (0.0, 0.3),
    "on the spot, 0.15 each way": (-0.15, 0.15),
    "on the spot, the other way": (0.15, -0.15),
    "straight, 0.3": (0.3, 0.3),
}
"""The programme's duties (truth 1: motor_gain 20, equal wheels, no dead-band or latency)."""
PHYSICS_HZ = 120


def follow(world: Any, mirror: WheelMotors, schedule: list[tuple[tuple[float, float], float]]
           ) -> list[dict[str, float]]:
    """Drive ``world`` through ``schedule`` ((duties, seconds) each) one physics sub-step at a
    time, beside ``mirror``, the same motor model fed the same duties: per segment, the robot's
    turn (deg) and the axle's path (mm), and what ideal kinematics make of the motor's
    velocity targets (the nominal wheel radius and track)."""
    geometry = Geometry()
    out = []
    k = 0
    for (left, right), seconds in schedule:
        world.set_duty(left, right)
        mirror.command(k, left, right)
        poses = [world.robot_pose()]
        turn = path = 0.0
        for _ in range(round(seconds * PHYSICS_HZ)):
            (wl, wr), _ = mirror.substep(k, None)
            turn += geometry.wheel_radius * (wr - wl) / geometry.track / PHYSICS_HZ
            path += geometry.wheel_radius * abs(wl + wr) / 2 / PHYSICS_HZ
            world.step(1 / PHYSICS_HZ)
            k += 1
            poses.append(world.robot_pose())
        xy = np.array(poses)
        out.append({"turn": math.degrees(float(np.unwrap(xy[:, 2])[-1] - xy[0, 2])),
                    "ideal_turn": math.degrees(turn),
                    "path": 1e3 * float(np.hypot(np.diff(xy[:, 0]), np.diff(xy[:, 1])).sum()),
                    "ideal_path": 1e3 * path})
    return out


def versus(actual: float, ideal: float) -> float | None:
    return round(100 * (actual / ideal - 1), 1) if abs(ideal) > 1e-6 else None


def kinematics(where: Path) -> list[dict[str, Any]]:
    """PyBullet's robot against ideal kinematics: one programme step (the duty for 0.25 s,
    then 0.3 s at rest), and the duty held (0.5..1.5 s: the lag settled)."""
    config = sim_config({**TRUTHS[0], "lens": "pinhole"}, where)
    robot = build_backend(config, BackendOptions(frame_size=FRAME_SIZE))
    assert isinstance(robot, SimRobot)
    world = robot.world
    scene = load_task(scene_task(config, BackendOptions())).scene(
        np.random.default_rng(config.sim.seed), False)
    rest = (0.0, 0.0)
    rows = []
    try:
        for name, duties in KINEMATICS.items():
            row: dict[str, Any] = {"case": name, "duties": list(duties)}
            for label, schedule, counted in (
                    ("step", [(rest, 0.5), (duties, 0.25), (rest, 0.3)], slice(1, 3)),
                    ("held", [(rest, 0.5), (duties, 0.5), (duties, 1.0)], slice(2, 3))):
                world.reset(scene=scene)
                segments = follow(world, WheelMotors(config.sim), schedule)[counted]
                total = {key: sum(s[key] for s in segments) for key in segments[0]}
                row[label] = {key: round(value, 2) for key, value in total.items()}
                row[label]["turn_vs_ideal_pct"] = versus(total["turn"], total["ideal_turn"])
                row[label]["path_vs_ideal_pct"] = (
                    versus(total["path"], total["ideal_path"]) if duties[0] == duties[1]
                    or 0.0 in duties else None)
            rows.append(row)
    finally:
        robot.disconnect()
    return rows


# -- the lens fit on exact corners ----------------------------------------------------------

def exact_corners(truth: Lens, images: list[np.ndarray], size: tuple[int, int]
                  ) -> list[np.ndarray]:
    """Each rendered view's board pose (solvePnP on the corners undistorted through the true
    lens), and the board's corners projected through the true lens from it: exact."""
    matrix, distortion = truth.matrix(*size), truth.distortion()
    board = board_points()
    out = []
    for view in board_views(images):
        rays = cv2.fisheye.undistortPoints(view, matrix, distortion).reshape(-1, 2)
        ok, rvec, tvec = cv2.solvePnP(board.reshape(-1, 3), rays, np.eye(3), None)
        assert ok
        points, _ = cv2.fisheye.projectPoints(board, rvec, tvec, matrix, distortion)
        out.append(points.reshape(1, -1, 2).astype(np.float64))
    return out


FLAGS_4X = sum(FISHEYE_FLAGS_4X.values())
"""The flags by OpenCV 4.x's numbers, as ``calibrate`` passed them before it named them
(``intrinsics.fisheye_flags``); on OpenCV 5 they are other flags."""


def opencv_alone(views: list[np.ndarray], size: tuple[int, int], flags: int
                 ) -> tuple[Lens, np.ndarray]:
    """``cv2.fisheye.calibrate`` as ``calibrate`` calls it (the same start and criteria;
    ``flags``), without the refinement; its lens and each corner's reprojection error (px)
    from the poses it returns."""
    board = board_points()
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    _, matrix, dist, rvecs, tvecs = cv2.fisheye.calibrate(
        [board] * len(views), views, size, Lens().matrix(*size), np.zeros((4, 1)),
        flags=flags, criteria=criteria)
    errors = []
    for view, rvec, tvec in zip(views, rvecs, tvecs, strict=True):
        points, _ = cv2.fisheye.projectPoints(board, rvec, tvec, matrix, dist)
        errors.append(np.linalg.norm(points.reshape(-1, 2) - view.reshape(-1, 2), axis=1))
    width, height = size
    focal = (matrix[0, 0] / width * SENSOR_ASPECT + matrix[1, 1] / height) / 2
    lens = Lens(focal, ((matrix[0, 2] + 0.5) / width, (matrix[1, 2] + 0.5) / height),
                tuple(float(k) for k in np.ravel(dist)))  # type: ignore[arg-type]
    return lens, np.concatenate(errors)


def lens_exact(name: str, truth: dict[str, Any]) -> dict[str, Any]:
    size = calibrate_command.CAMERA_FRAME_SIZE["sim"]
    sim = dataclasses.replace(Config().sim, lens="fisheye", **truth)
    want = Lens.from_sim(sim)
    views = exact_corners(want, sim_views(sim, size, 15), size)
    row: dict[str, Any] = {"name": name, "truth": truth, "views": len(views)}
    for label, flags in (("opencv", FLAGS_4X), ("opencv_own_flags", fisheye_flags())):
        lens, errors = opencv_alone(views, size, flags)
        row[label] = {"flags": flags,
                      "rms_px": float(f"{math.sqrt(np.mean(errors ** 2)):.3g}"),
                      "max_px": float(f"{errors.max():.3g}"),
                      "focal_error_pct": float(f"{100 * (lens.focal / want.focal - 1):.3g}"),
                      "radial_error_px": [float(f"{v:.3g}") for v in
                                          radial_error_px(want, lens)]}
    fitted = calibrate(views, size)
    row["refined"] = {"rms_px": float(f"{fitted.rms_px:.2g}"),
                      "focal_error_pct": float(f"{100 * (fitted.lens.focal / want.focal - 1):.2g}"),
                      "radial_error_px": [float(f"{v:.2g}") for v in
                                          radial_error_px(want, fitted.lens)]}
    return row


# -- the report -----------------------------------------------------------------------------

def drive_table(rows: list[dict[str, Any]], lens: str) -> list[str]:
    lines = [f"### Drives through the {lens}", "",
             "| truth | true motor_gain | true wheel_gain | true deadband | true latency ms | "
             "fitted left gain | fitted right gain | fitted wheel_gain | fitted deadband L / R "
             f"| latency ms | tau ms (true {TAU_TRUE * 1e3:g}) | track mm | rms mm / deg | "
             "fit s | drive wall s | moved cm / turned deg | left, right gain error without "
             "the rest weight |", "|" + " --- |" * 17]
    for r in rows:
        if r["lens"] != lens:
            continue
        if r["exit_code"]:
            lines.append(f"| {r['truth']} | exit {r['exit_code']} |" + " |" * 15)
            continue
        t = TRUTHS[r["truth"] - 1]
        latency = f"{r['true_latency'] * 1e3:g}"
        if t.get("camera_latency"):
            latency += f" ({t['latency'] * 1e3:g} + {t['camera_latency'] * 1e3:g} camera)"
        e, m = r["gain_error_pct"], r["moved"]
        lines.append(
            f"| {r['truth']} | {t['motor_gain']:g} | {t['wheel_gain']} | {t['deadband']:g} | "
            f"{latency} | {r['gain'][0]:.2f} ({e[0]:+.1f} %) | {r['gain'][1]:.2f} "
            f"({e[1]:+.1f} %) | [{r['wheel_gain'][0]:.3f}, {r['wheel_gain'][1]:.3f}] | "
            f"{r['deadband_lr'][0]:.3f} / {r['deadband_lr'][1]:.3f} | {r['latency_ms']:.1f} | "
            f"{r['tau_ms']:.0f} | {r['track_mm']:.0f} | {r['rms_mm']:.1f} / {r['rms_deg']:.2f} "
            f"| {r['fit_s']} | {r['wall_s']} | {m['max_distance_cm']} / {m['max_turn_deg']} | "
            f"{r['unweighted_gain_error_pct'][0]:+.1f}, {r['unweighted_gain_error_pct'][1]:+.1f}"
            " % |")
    return [*lines, ""]


def seen_over(rows: list[dict[str, Any]], lens: str) -> dict[str, Any]:
    """The largest error over a lens's drives, as the doc's tolerances are stated."""
    ok = [r for r in rows if r["lens"] == lens and not r["exit_code"]]
    if not ok:
        return {}
    return {
        "drives": len(ok),
        "gain_error_pct": max(abs(e) for r in ok for e in r["gain_error_pct"]),
        "motor_gain_error_pct": max(abs(r["motor_gain_error_pct"]) for r in ok),
        "wheel_gain_error": max(r["wheel_gain_error"] for r in ok),
        "deadband_error": round(max(abs(d - r["true_deadband"]) for r in ok
                                    for d in r["deadband_lr"]), 4),
        "latency_error_ms": max(abs(r["latency_error_ms"]) for r in ok),
        "tau_ms": [min(r["tau_ms"] for r in ok), max(r["tau_ms"] for r in ok)],
        "track_mm": [min(r["track_mm"] for r in ok), max(r["track_mm"] for r in ok)],
        "unweighted_gain_error_pct": max(abs(e) for r in ok
                                         for e in r["unweighted_gain_error_pct"]),
        "moved_cm": [min(r["moved"]["max_distance_cm"] for r in ok),
                     max(r["moved"]["max_distance_cm"] for r in ok)],
        "turned_deg": [min(r["moved"]["max_turn_deg"] for r in ok),
                       max(r["moved"]["max_turn_deg"] for r in ok)],
        "fit_s": [min(r["fit_s"] for r in ok), max(r["fit_s"] for r in ok)],
        "error_over_sigma": {key: max(r["error_over_sigma"][key] for r in ok)
                             for key in ok[0]["error_over_sigma"]},
    }


ERROR_KEYS = ("gain_left", "gain_right", "deadband_left", "deadband_right", "latency")


def markdown(result: dict[str, Any]) -> str:
    m = result["machine"]
    lines = ["# Drive calibration: recovered versus true, and what is behind it", "",
             f"`{result['command']}`, {result['date']}, {m['cpu']}, {m['cores']} cores, 1-min "
             f"load average {m['loadavg_1min_at_start']} at start, {m['loadavg_1min_at_end']} "
             f"at the end (other jobs' load included); {result['wall_s']} s in all. Versions "
             "in calibration.json.", ""]
    drives = result.get("drives", [])
    if drives:
        lines += ["## The drive: `jetbot-rt calibrate --backend sim --config TRUTH --yes`", "",
                  "Per-wheel gains are rad/s at duty 1, errors relative to the truth's; "
                  "latency is `latency + camera_latency`; fit s: the fit of the recording "
                  "alone, in this process; moved / turned: the farthest the programme took "
                  "the robot from its start.", ""]
        for lens in LENSES:
            if any(r["lens"] == lens for r in drives):
                lines += drive_table(drives, lens)
        lines += ["### Largest errors over each lens's drives", "",
                  "| lens | drives | gain | motor_gain | wheel_gain | dead-band | latency ms "
                  "| tau ms | track mm | gain without the rest weight | moved cm | turned deg "
                  "| fit s |", "|" + " --- |" * 13]
        for lens, s in result["seen_over"].items():
            if s:
                lines.append(
                    f"| {lens} | {s['drives']} | {s['gain_error_pct']} % | "
                    f"{s['motor_gain_error_pct']} % | {s['wheel_gain_error']} | "
                    f"{s['deadband_error']} | {s['latency_error_ms']} | "
                    f"{s['tau_ms'][0]:.0f}..{s['tau_ms'][1]:.0f} | "
                    f"{s['track_mm'][0]:.0f}..{s['track_mm'][1]:.0f} | "
                    f"{s['unweighted_gain_error_pct']} % | "
                    f"{s['moved_cm'][0]}..{s['moved_cm'][1]} | "
                    f"{s['turned_deg'][0]}..{s['turned_deg'][1]} | "
                    f"{s['fit_s'][0]}..{s['fit_s'][1]} |")
        lines += ["", "### The real errors over the fit's standard errors (largest over each "
                  "lens's drives)", "", "| lens | " + " | ".join(ERROR_KEYS) + " |",
                  "|" + " --- |" * (len(ERROR_KEYS) + 1)]
        for lens, s in result["seen_over"].items():
            if s:
                lines.append(f"| {lens} | " + " | ".join(
                    str(s["error_over_sigma"][key]) for key in ERROR_KEYS) + " |")
        lines.append("")
    if result.get("marker"):
        lines += [f"## The marker in one frame, {MARKER_DISTANCE} m ahead of the axle, "
                  f"{FRAME_SIZE[0]}x{FRAME_SIZE[1]}", "",
                  "Measured minus true; mean +- sd and largest |error| over bearings "
                  f"{BEARINGS_DEG[0]}..{BEARINGS_DEG[-1]} degrees (step 5).", "",
                  "| lens | found | true range m at 0 | range error mm at 0 | range error mm "
                  "| largest mm | bearing error deg at 0 | bearing error deg | largest deg |",
                  "|" + " --- |" * 9]
        for s in result["marker"]:
            r, b = s["range_error_mm"], s["bearing_error_deg"]
            zero = next(row for row in s["rows"] if row["bearing_deg"] == 0)
            lines.append(
                f"| {s['lens']} | {s['found']} of {s['of']} | {zero['true_range_m']} | "
                f"{r['at_0']} | {r['mean']} +- {r['sd']} | {r['max_abs']} | {b['at_0']} | "
                f"{b['mean']} +- {b['sd']} | {b['max_abs']} |")
        lines.append("")
    if result.get("kinematics"):
        lines += ["## PyBullet's robot against ideal kinematics", "",
                  "Truth 1 (motor_gain 20, equal wheels, no dead-band or latency). Ideal: the "
                  "motor model's velocity targets through differential-drive kinematics on the "
                  "nominal wheel radius 0.03 m and track 0.11 m. Step: the duty for 0.25 s and "
                  "0.3 s at rest, as in the programme; held: 0.5..1.5 s of the duty held.", "",
                  "| duties (left, right) | case | step: turn deg (ideal) | vs ideal | path mm "
                  "(ideal) | vs ideal | held: turn deg (ideal) | vs ideal | path mm (ideal) | "
                  "vs ideal |", "|" + " --- |" * 10]
        for k in result["kinematics"]:
            cells = []
            for label in ("step", "held"):
                r = k[label]
                for key in ("turn", "path"):
                    pct = r[f"{key}_vs_ideal_pct"]
                    cells += [f"{r[key]} ({r['ideal_' + key]})",
                              "-" if pct is None else f"{pct:+.1f} %"]
            lines.append(f"| {k['duties']} | {k['case']} | " + " | ".join(cells) + " |")
        lines.append("")
    if result.get("lens_exact"):
        lines += ["## The lens fit on exact synthetic corners, 640x360", "",
                  "The sim's board views (15 poses), each re-projected through the true lens "
                  "from its pose: corners with no error. OpenCV alone: `cv2.fisheye.calibrate` "
                  "from the datasheet lens, with the flags by OpenCV 4.x's numbers "
                  f"({FLAGS_4X}: what `calibrate` passed before) and by this OpenCV's own "
                  f"({fisheye_flags()}: what it passes now); the rms and largest corner error from "
                  "the poses it returns. Refined: `calibrate` (OpenCV, then the joint "
                  "refinement). Radial error: image radius per ray against the truth's, px, to "
                  "the side edge / corner. The datasheet lens is OpenCV's start.", "",
                  "| truth | views | fit | rms px | largest px | focal error % | radial error px "
                  "|", "|" + " --- |" * 7]
        for r in result["lens_exact"]:
            for label, fit in (("OpenCV, 4.x's flag numbers (before)", r["opencv"]),
                               ("OpenCV, its own flag values (now)", r["opencv_own_flags"]),
                               ("refined (calibrate)", r["refined"])):
                lines.append(
                    f"| {r['name']} | {r['views']} | {label} | {fit['rms_px']} | "
                    f"{fit.get('max_px', '-')} | {fit['focal_error_pct']} | "
                    f"{fit['radial_error_px'][0]} / {fit['radial_error_px'][1]} |")
        lines.append("")
    return "\n".join(lines)


PARTS = ("drive", "marker", "kinematics", "lens")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    parser.add_argument("--only", default=",".join(PARTS),
                        help=f"comma-separated parts to run (default: all of {PARTS})")
    args = parser.parse_args()
    parts = args.only.split(",")
    t0 = time.perf_counter()
    result: dict[str, Any] = {
        **run_record(), "machine": machine(), "truths": TRUTHS, "lenses": LENSES}
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(tmp)
        if "lens" in parts:
            result["lens_exact"] = [lens_exact(n, t) for n, t in LENS_TRUTHS.items()]
            print(json.dumps(result["lens_exact"]), flush=True)
        if "kinematics" in parts:
            result["kinematics"] = kinematics(where)
            print(json.dumps(result["kinematics"]), flush=True)
        if "marker" in parts:
            result["marker"] = [marker(lens, where) for lens in LENSES]
            print(json.dumps([{k: v for k, v in s.items() if k != "rows"}
                              for s in result["marker"]]), flush=True)
        if "drive" in parts:
            result["drives"] = []
            for index, lens in DRIVES:
                run = where / f"drive-{index + 1}-{lens.replace(' ', '-')}"
                run.mkdir()
                result["drives"].append(drive(index, lens, run))
                print(json.dumps({k: v for k, v in result["drives"][-1].items()
                                  if k != "toml"}), flush=True)
            result["seen_over"] = {lens: seen_over(result["drives"], lens) for lens in LENSES}
    result["machine"]["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    result["wall_s"] = round(time.perf_counter() - t0)
    write_results(args.out, "calibration", result, markdown(result))


if __name__ == "__main__":
    main()
