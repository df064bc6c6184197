"""The physics and lens facts docs/SIM.md quotes, re-measured in one run with today's code:
the ideal motor against a wall, the DC motor (``stall_torque = 0.078``) against a wall and
from rest (measured as tests/test_sim_imperfections.py measures them), the goal block pushed
at each duty, the DC motor's heading bias on straight runs, and the time to build a lens's
map.

    python benchmarks/bench_sim_facts.py [--rounds 20] [--out benchmarks/results]

The physics runs are deterministic (one run each, today's [sim] defaults otherwise: physics
at ``SimConfig().physics_hz``); the lens maps are timed in interleaved rounds, medians of
wall times. Writes sim_facts.json and sim_facts.md to --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from bench_sim import machine
from bench_sim_choices import in_rounds
from versions import run_record, write_results

from jetbot_rt.calibration.intrinsics import Lens
from jetbot_rt.sim.config import SimConfig
from jetbot_rt.sim.lens import FisheyeWarp
from jetbot_rt.sim.probes import SIZE, TICK, drive_straight, wall_push
from jetbot_rt.sim.pybullet_import import import_pybullet
from jetbot_rt.sim.world import JetbotWorld

p = import_pybullet()

PINHOLE = SimConfig(lens="pinhole")
STALL = 0.078
"""N m: the TT 1:48 motor's stall torque (docs/SIM.md, "Torque")."""
DC = dataclasses.replace(PINHOLE, stall_torque=STALL)
WHEEL_RADIUS = 0.03
PUSH_DUTIES = (0.1, 0.2, 0.5, 1.0)
HEADINGS = tuple(k * math.pi / 4 for k in range(8))
LENS_SIZES = (56, 224)


def wall_push_figures(config: SimConfig, duty: float) -> dict[str, float]:
    """``probes.wall_push`` (tests/test_sim_imperfections.py's measurement): its mean, least
    and largest force and the wheel's speed."""
    forces, spin = wall_push(config, duty)
    return {"force_n": round(float(np.mean(forces)), 3),
            "force_min_n": round(float(np.min(forces)), 3),
            "force_max_n": round(float(np.max(forces)), 3),
            "wheel_speed_rad_s": round(spin, 3)}


# 1. The ideal motor against a wall ---------------------------------------------------------


def ideal_wall() -> dict[str, Any]:
    """The ideal motor (today's default ``[sim]``) pushing the wall at duty 0.2 (the doc's
    figure) and at 0.6 and 1.0."""
    return {f"{d:g}": wall_push_figures(SimConfig(), d) for d in (0.2, 0.6, 1.0)}


# 2. The DC motor against a wall, and from rest ---------------------------------------------


def dc_motor() -> dict[str, Any]:
    """``stall_torque = 0.078`` as test_stall_torque_makes_torque_scale_with_duty measures
    it: the wall at duty 0.2 and 0.6 against the nominal ``2 * stall * d / r``; 2 s straight
    from rest at duty 0.1 against the ideal motor: the distance after 0.1 s (3 ticks) and the
    free-running speed (from 1 s on)."""
    wall = {}
    for d in (0.2, 0.6):
        wall[f"{d:g}"] = {**wall_push_figures(DC, d),
                          "nominal_n": round(2 * STALL * d / WHEEL_RADIUS, 3)}
        wall[f"{d:g}"]["ratio_to_nominal"] = round(
            wall[f"{d:g}"]["force_n"] / wall[f"{d:g}"]["nominal_n"], 3)
    ideal, slow = (drive_straight(c, 0.1, 2.0, pose=(-0.6, 0.0, 0.0)) for c in (SimConfig(), DC))
    start = [float(x[3, 0] - x[0, 0]) for x in (ideal, slow)]
    speeds = [float((x[-1, 0] - x[30, 0]) / ((len(x) - 31) * TICK)) for x in (ideal, slow)]
    return {"wall": wall,
            "start_0.1s_mm": {"ideal": round(1e3 * start[0], 3), "dc": round(1e3 * start[1], 3),
                              "ratio": round(start[1] / start[0], 3)},
            "free_speed_m_s": {"ideal": round(speeds[0], 4), "dc": round(speeds[1], 4),
                               "ratio": round(speeds[1] / speeds[0], 4)}}


# 3. The goal block ---------------------------------------------------------------------------


def block_push(config: SimConfig, duty: float, seconds: float = 3.0) -> dict[str, float]:
    """The robot 0.2 m behind the block, both facing +x, driving at ``duty`` until it has
    pushed for ``seconds``: over the push after its first 0.5 s, the force on the block along
    the heading (N, mean) and ``distance_to_block()`` (m, min / max); and the share of ticks
    from the first touch on that the robot touched the block."""
    world = JetbotWorld(config, image_size=SIZE)
    try:
        world.reset(robot_pose=(-1.2, 0.0, 0.0), block_xy=(-1.0, 0.0))
        world.set_duty(duty, duty)
        touched_at = None
        forces, distances, touching = [], [], []
        while world.sim_time < 30.0:
            world.step(TICK)
            touch = world.touching("goal")
            if touched_at is None and touch:
                touched_at = world.sim_time
            if touched_at is None:
                continue
            if world.sim_time > touched_at + seconds:
                break
            touching.append(touch)
            if world.sim_time > touched_at + 0.5:
                contacts = p.getContactPoints(world._robot, world._body("goal"),
                                              physicsClientId=world._client)
                forces.append(-sum(c[9] * c[7][0] for c in contacts))  # along +x
                distances.append(world.distance_to_block())
        if touched_at is None:
            raise RuntimeError(f"duty {duty}: the robot never reached the block")
        return {"force_n": round(float(np.mean(forces)), 3),
                "distance_min_m": round(float(np.min(distances)), 4),
                "distance_max_m": round(float(np.max(distances)), 4),
                "touching_pct": round(100 * float(np.mean(touching)), 1),
                "block_pushed_m": round(world.block_shift(), 3),
                "reached_after_s": round(touched_at, 3)}
    finally:
        world.close()


def goal_block() -> dict[str, Any]:
    """The block pushed at each duty by the ideal motor and the DC motor, against the
    friction that slides it (``mu * m * g``: PyBullet multiplies the block's 0.5 by the
    floor's 1) and the ideal motor's push against the wall (fact 1)."""
    friction = 0.5 * 1.0 * 0.2 * 9.81
    return {"coulomb_friction_n": round(friction, 3),
            "ideal": {f"{d:g}": block_push(SimConfig(), d) for d in PUSH_DUTIES},
            "dc": {f"{d:g}": block_push(DC, d) for d in PUSH_DUTIES}}


# 4. The DC motor's heading bias --------------------------------------------------------------


def heading_bias() -> dict[str, Any]:
    """2 s straight at duty 0.5 from the room's centre, at eight headings (block out of the
    way): the angle turned (rad; negative: clockwise), the ideal motor and the DC motor, at
    today's physics rate and at 240 Hz (the default before 120 Hz)."""
    out: dict[str, Any] = {}
    for name, config in (("ideal", SimConfig()), ("dc", DC),
                         ("ideal 240 Hz", SimConfig(physics_hz=240.0)),
                         ("dc 240 Hz", dataclasses.replace(DC, physics_hz=240.0))):
        turned = []
        for yaw in HEADINGS:
            poses = drive_straight(config, 0.5, 2.0, pose=(0.0, 0.0, yaw), block_xy=(-1.3, -1.3)
                             if math.cos(yaw) + math.sin(yaw) > 0 else (1.3, 1.3))
            turned.append(float(np.unwrap(poses[:, 2])[-1] - poses[0, 2]))
        out[name] = {"per_heading_rad": {f"{math.degrees(y):.0f}": round(t, 5)
                                         for y, t in zip(HEADINGS, turned, strict=True)},
                     "min_rad": round(min(turned), 5), "max_rad": round(max(turned), 5),
                     "max_abs_rad": round(max(abs(t) for t in turned), 5)}
    return out


# 5. A lens's map ---------------------------------------------------------------------------


def lens_map(rounds: int, repeats: int) -> dict[str, Any]:
    """``FisheyeWarp`` (what ``lens_warp`` builds once per lens, uncached here) for today's
    default lens, per frame size: median ms."""
    lens = Lens.from_sim(SimConfig())
    seconds: dict[int, list[float]] = {s: [] for s in LENS_SIZES}
    for size in in_rounds(list(LENS_SIZES), rounds):
        for _ in range(repeats):
            t = time.perf_counter()
            FisheyeWarp(lens, (size, size))
            seconds[size].append(time.perf_counter() - t)
    return {"builds_per_size": rounds * repeats,
            "median_ms": {str(s): round(1e3 * float(np.median(v)), 3)
                          for s, v in seconds.items()},
            "p90_ms": {str(s): round(1e3 * float(np.percentile(v, 90)), 3)
                       for s, v in seconds.items()}}


# Report --------------------------------------------------------------------------------------


def markdown(r: dict[str, Any]) -> str:
    m, w, dc, g, b, lm = (r["machine"], r["ideal_wall"], r["dc_motor"], r["goal_block"],
                          r["heading_bias"], r["lens_map"])
    lines = [
        "# docs/SIM.md's physics and lens facts, re-measured", "",
        f"Command: `{r['command']}`  ",
        f"Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}; 1-min load average "
        f"{m['loadavg_1min_at_start']} at start, {m['loadavg_1min_at_end']} at the end  ",
        f"Date: {r['date']}; versions in sim_facts.json. Physics at {r['physics_hz']:g} Hz "
        "(today's default), one deterministic run each; timings: medians of wall times.", "",
        "## 1. The ideal motor against a wall", "",
        "Today's default `[sim]` (`stall_torque` unset), started 4 cm from the +x wall: the "
        "force against it averaged over the second half of 1 s (min / max over those ticks), "
        "and the fastest wheel at the end (as `_wall_push` in "
        "tests/test_sim_imperfections.py).", "",
        "| duty | force | min / max | wheel speed |", "| --- | --- | --- | --- |",
        *(f"| {d} | {v['force_n']:.2f} N | {v['force_min_n']:.2f} / {v['force_max_n']:.2f} N "
          f"| {v['wheel_speed_rad_s']:.2f} rad/s |" for d, v in w.items()),
        "", f"## 2. `stall_torque = {STALL}` (the DC motor)", "",
        "Against the wall as above; nominal `2 * stall * d / r`:", "",
        "| duty | force | nominal | ratio | wheel speed |", "| --- | --- | --- | --- | --- |",
        *(f"| {d} | {v['force_n']:.2f} N | {v['nominal_n']:.2f} N | "
          f"x{v['ratio_to_nominal']:.2f} | {v['wheel_speed_rad_s']:.3f} rad/s |"
          for d, v in dc["wall"].items()),
        "", f"From rest at duty 0.1: {dc['start_0.1s_mm']['dc']:.2f} mm in the first 0.1 s "
        f"against the ideal motor's {dc['start_0.1s_mm']['ideal']:.2f} mm "
        f"({100 * dc['start_0.1s_mm']['ratio']:.0f} %); free running (1-2 s) "
        f"{dc['free_speed_m_s']['dc']:.4f} m/s against {dc['free_speed_m_s']['ideal']:.4f} "
        f"(x{dc['free_speed_m_s']['ratio']:.3f}).", "",
        "## 3. The goal block pushed", "",
        "The robot 0.2 m behind the block, both facing +x, driving at the duty until it has "
        "pushed for 3 s. Over the push after its first 0.5 s: the robot's force on the block "
        "along +x (mean) and `distance_to_block()` (min / max); the share of ticks from the "
        "first touch on with the robot touching the block; how far the block moved. Sliding "
        f"friction `mu * m * g` = {g['coulomb_friction_n']:.2f} N.", "",
        "| motor | duty | force on the block | distance_to_block() | touching | block moved |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for motor in ("ideal", "dc"):
        for d, v in g[motor].items():
            lines.append(f"| {motor} | {d} | {v['force_n']:.2f} N | {v['distance_min_m']:.4f} "
                         f"/ {v['distance_max_m']:.4f} m | {v['touching_pct']:.1f} % | "
                         f"{v['block_pushed_m']:.2f} m |")
    lines += [
        "", "## 4. Heading bias: 2 s straight at duty 0.5", "",
        "From the room's centre at eight headings; the angle turned (rad, negative: "
        f"clockwise); at {r['physics_hz']:g} Hz unless the row says otherwise.", "",
        "| motor | " + " | ".join(f"{h} deg" for h in b["ideal"]["per_heading_rad"]) +
        " | range |", "| --- |" + " --- |" * (len(HEADINGS) + 1),
        *(f"| {motor} | " + " | ".join(f"{t:+.4f}" for t in b[motor]["per_heading_rad"].values())
          + f" | {b[motor]['min_rad']:+.4f} .. {b[motor]['max_rad']:+.4f} |"
          for motor in b),
        "", "## 5. A lens's map", "",
        f"`FisheyeWarp` for the default lens, {lm['builds_per_size']} builds a size "
        "(interleaved rounds): " + ", ".join(
            f"{lm['median_ms'][str(s)]:.2f} ms at {s}x{s} (p90 {lm['p90_ms'][str(s)]:.2f})"
            for s in LENS_SIZES) + ".",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()
    result: dict[str, Any] = {
        **run_record(), "machine": machine(), "rounds": args.rounds,
        "physics_hz": SimConfig().physics_hz}
    steps: list[tuple[str, Callable[[], Any]]] = [
        ("ideal_wall", ideal_wall), ("dc_motor", dc_motor), ("goal_block", goal_block),
        ("heading_bias", heading_bias), ("lens_map", lambda: lens_map(args.rounds, 5)),
    ]
    for key, run in steps:
        t = time.perf_counter()
        result[key] = run()
        print(f"{key}: {time.perf_counter() - t:.0f} s", flush=True)
    result["machine"]["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    write_results(args.out, "sim_facts", result, markdown(result))


if __name__ == "__main__":
    main()
