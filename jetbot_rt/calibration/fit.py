"""The fit: a model of the robot (per wheel: gain and dead-band, one command-to-image latency,
one first-order time constant; differential-drive kinematics on the known wheel radius and
track) predicts the marker's range and bearing at each frame from the recorded duties; a
Levenberg-Marquardt fit (numpy) adjusts the model until the prediction matches what the camera
saw. Uncertainties are the fit's formal standard errors scaled by its residuals; frames are
not independent (the model's own error is correlated in time), so they are optimistic:
docs/CALIBRATION.md gives the errors measured against known truths.

Why a model and not slopes per step: a step is short (the marker must stay in view), so the
lag and the latency take a large part of it, and the dead-band, gain, latency and lag are only
told apart by fitting them together over every step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from jetbot_rt.calibration.measure import Geometry

NAMES = ("gain_left", "gain_right", "deadband_left", "deadband_right", "latency", "tau",
         "range0", "heading0", "track")
LOW = np.array([0.1, 0.1, 0.0, 0.0, 0.0, 0.0, 0.05, -1.0, 0.02])
HIGH = np.array([500.0, 500.0, 0.95, 0.95, 0.6, 0.5, 5.0, 1.0, 1.0])
SIGMA_RANGE = 0.003
SIGMA_BEARING = 0.004
REST_WEIGHT = 5.0
"""Residual scales (m, rad): what the marker's corners give at 0.5 m in a 320x180 frame."""


@dataclass
class Data:
    """Per tick: when the duties were written (s), the duties, and what that tick's frame
    showed (range m, bearing rad; nan where the marker was not found)."""

    t: np.ndarray
    duties: np.ndarray
    reach: np.ndarray
    bearing: np.ndarray


@dataclass
class Result:
    values: dict[str, float]
    sigma: dict[str, float]
    rms_range_mm: float
    rms_bearing_deg: float
    frames: int


def predict(p: np.ndarray, data: Data, geometry: Geometry, dt: float) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    g = p[0:2]
    db = p[2:4]
    latency, tau, range0, heading0 = p[4], p[5], p[6], p[7]
    duty = data.duties
    steady = g * np.sign(duty) * np.maximum(np.abs(duty) - db, 0.0)  # rad/s per tick, 2 wheels
    t = data.t
    grid = np.arange(t[0], t[-1] + dt, dt)
    # the piecewise-constant command's integral, delayed by the latency, sampled on the grid:
    # each grid cell gets the command's exact mean over it (continuous in the latency)
    knots = np.append(t, t[-1] + 1e3) + latency
    widths = np.diff(knots)
    u = np.empty((len(grid) - 1, 2))
    for w in (0, 1):
        integral = np.concatenate(([0.0], np.cumsum(steady[:, w] * widths)))
        u[:, w] = np.diff(np.interp(grid, knots, integral)) / dt
    decay = math.exp(-dt / tau) if tau > 1e-6 else 0.0
    omega = np.empty((len(grid), 2))
    left = right = 0.0
    omega[0] = 0.0
    ul, ur = u[:, 0].tolist(), u[:, 1].tolist()
    out_l, out_r = [0.0], [0.0]
    for n in range(len(ul)):
        left = ul[n] + (left - ul[n]) * decay
        right = ur[n] + (right - ur[n]) * decay
        out_l.append(left)
        out_r.append(right)
    omega[:, 0], omega[:, 1] = out_l, out_r
    mid = (omega[1:] + omega[:-1]) / 2 * geometry.wheel_radius
    speed = mid.sum(axis=1) / 2
    turn = (mid[:, 1] - mid[:, 0]) / p[8]
    heading = heading0 + np.concatenate(([0.0], np.cumsum(turn * dt)))
    mid_heading = (heading[1:] + heading[:-1]) / 2
    x = -range0 + np.concatenate(([0.0], np.cumsum(speed * np.cos(mid_heading) * dt)))
    y = np.concatenate(([0.0], np.cumsum(speed * np.sin(mid_heading) * dt)))
    xs, ys, hs = (np.interp(t, grid, v) for v in (x, y, heading))
    cx = xs + geometry.camera_offset * np.cos(hs)
    cy = ys + geometry.camera_offset * np.sin(hs)
    reach = np.hypot(cx, cy)
    bearing = -(np.arctan2(-cy, -cx) - hs)
    bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
    return reach, bearing


def _residuals(p: np.ndarray, data: Data, geometry: Geometry, dt: float,
               seen: np.ndarray) -> np.ndarray:
    reach, bearing = predict(p, data, geometry, dt)
    weight = _weights(data)[seen]
    return np.concatenate(((reach[seen] - data.reach[seen]) / SIGMA_RANGE * weight,
                           (bearing[seen] - data.bearing[seen]) / SIGMA_BEARING * weight))


def _weights(data: Data) -> np.ndarray:
    """The frames before the first step weigh REST_WEIGHT times more: they tell where the
    robot started, and a model that misses some of the motion must not move the start."""
    moved = np.cumsum(np.abs(data.duties).sum(axis=1)) > 0
    return np.where(moved, 1.0, REST_WEIGHT)


def _jacobian(p: np.ndarray, r0: np.ndarray, *args: object) -> np.ndarray:
    jac = np.empty((len(r0), len(p)))
    for i in range(len(p)):
        h = 1e-4 * max(abs(p[i]), 0.05)
        q = p.copy()
        q[i] = q[i] + h if q[i] + h <= HIGH[i] else q[i] - h
        jac[:, i] = (_residuals(q, *args) - r0) / (q[i] - p[i])  # type: ignore[arg-type]
    return jac


def _levenberg_marquardt(p: np.ndarray, args: tuple, iterations: int = 40
                         ) -> tuple[np.ndarray, float, np.ndarray]:
    r = _residuals(p, *args)
    cost = float(r @ r)
    damping = 1e-2
    jac = _jacobian(p, r, *args)
    for _ in range(iterations):
        a = jac.T @ jac
        b = jac.T @ r
        step = np.linalg.solve(a + damping * np.diag(np.diag(a) + 1e-9), -b)
        q = np.clip(p + step, LOW, HIGH)
        rq = _residuals(q, *args)
        cq = float(rq @ rq)
        if cq < cost:
            improved = (cost - cq) / max(cost, 1e-12)
            p, r, cost = q, rq, cq
            damping = max(damping / 3, 1e-7)
            jac = _jacobian(p, r, *args)
            if improved < 1e-7:
                break
        else:
            damping *= 4
            if damping > 1e8:
                break
    return p, cost, jac


def fit(data: Data, geometry: Geometry, max_duty: float) -> Result:
    seen = np.isfinite(data.reach) & np.isfinite(data.bearing)
    if seen.sum() < 30:
        raise ValueError(f"the marker was seen in {int(seen.sum())} frames; too few to fit")
    period = float(np.median(np.diff(data.t)))
    dt = period / 6
    first = np.flatnonzero(seen)[0]
    start = np.array([20.0, 20.0, 0.05, 0.05, 0.05, 0.05,
                      data.reach[first] + geometry.camera_offset, -data.bearing[first],
                      geometry.track])
    args = (data, geometry, dt, seen)
    best = None
    for latency in (0.0, 0.1, 0.2):
        for gain in (10.0, 30.0):
            p0 = start.copy()
            p0[4] = latency
            p0[0:2] = gain
            p, cost, jac = _levenberg_marquardt(p0, args)
            if best is None or cost < best[1]:
                best = (p, cost, jac)
    assert best is not None
    p, cost, jac = best
    dof = max(len(jac) - len(p), 1)
    scale = cost / dof
    try:
        cov = np.linalg.inv(jac.T @ jac) * scale
        sigma = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        sigma = np.full(len(p), np.inf)
    reach, bearing = predict(p, data, geometry, dt)
    return Result(
        values=dict(zip(NAMES, (float(v) for v in p))),
        sigma=dict(zip(NAMES, (float(v) for v in sigma))),
        rms_range_mm=float(np.sqrt(np.mean((reach[seen] - data.reach[seen]) ** 2)) * 1e3),
        rms_bearing_deg=float(np.degrees(np.sqrt(np.mean(
            (bearing[seen] - data.bearing[seen]) ** 2)))),
        frames=int(seen.sum()),
    )


def sim_table(result: Result, geometry: Geometry) -> list[tuple[str, str, str]]:
    """The ``[sim]`` keys (name, TOML value, comment): the stronger wheel's gain is
    ``motor_gain`` and its ``wheel_gain`` 1 (a weak wheel is the one below 1); one dead-band
    (the mean of the wheels', the sim has one); the whole command-to-image latency in
    ``latency``, ``camera_latency`` 0 (the camera alone cannot tell them apart)."""
    v, s = result.values, result.sigma
    gl, gr = v["gain_left"], v["gain_right"]
    strong = max(gl, gr)
    strong_sigma = s["gain_left"] if gl >= gr else s["gain_right"]
    rel = math.hypot(s["gain_left"] / gl, s["gain_right"] / gr)
    wheel = (gl / strong, gr / strong)
    deadband = (v["deadband_left"] + v["deadband_right"]) / 2
    deadband_sigma = math.hypot(s["deadband_left"], s["deadband_right"]) / 2
    return [
        ("motor_gain", f"{strong:.3f}", f"+- {strong_sigma:.2f} rad/s at duty 1 (the stronger "
         f"wheel; radius {geometry.wheel_radius:g} m)"),
        ("wheel_gain", f"[{wheel[0]:.4f}, {wheel[1]:.4f}]", f"+- {rel:.4f} (the weaker wheel)"),
        ("deadband", f"{deadband:.4f}", f"+- {deadband_sigma:.4f}; left {v['deadband_left']:.4f}"
         f" +- {s['deadband_left']:.4f}, right {v['deadband_right']:.4f} +- "
         f"{s['deadband_right']:.4f}"),
        ("latency", f"{v['latency']:.4f}", f"+- {s['latency']:.4f} s: command to image, all of "
         "it (motor and camera)"),
        ("camera_latency", "0.0", "in latency above: the camera alone cannot split them"),
        ("motor_tau", f"{v['tau']:.4f}", f"+- {s['tau']:.4f} s (fitted track "
         f"{v['track']:.4f} +- {s['track']:.4f} m, nominal {geometry.track:g})"),
    ]


def to_toml(result: Result, geometry: Geometry, source: str) -> str:
    lines = [f"# jetbot-rt calibrate: fitted from {source}",
             f"# {result.frames} frames with the marker; residuals rms "
             f"{result.rms_range_mm:.1f} mm in range, {result.rms_bearing_deg:.2f} degrees in "
             "bearing. Uncertainties are the fit's standard errors (optimistic).",
             "", "[sim]"]
    lines += [f"{key} = {value}  # {comment}" for key, value, comment in
              sim_table(result, geometry)]
    v = result.values
    latency = v["latency"]
    deadband = (v["deadband_left"] + v["deadband_right"]) / 2
    lines += ["", "# Training draws around the measured robot: [sim] motor_gain and wheel_gain "
              "are multiplied", "# by [randomize]'s factors; the value ranges below are "
              "centred on what was measured.", "[randomize]",
              f"deadband = [{max(0.0, deadband - 0.05):.3f}, {min(0.98, deadband + 0.05):.3f}]",
              f"latency = [{max(0.0, latency - 0.03):.3f}, {min(1.0, latency + 0.05):.3f}]",
              "camera_latency = [0.0, 0.0]", ""]
    return "\n".join(lines)
