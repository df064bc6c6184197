"""The experts' design choices, measured against the alternatives they replaced (docs/TRAINING.md,
"Training seek by DAgger"; docs/BENCHMARKS.md, "Training the policies"): each expert drives
the evaluation's episodes (seeds from 10000, the task's randomization unless a condition file
turns it off) on the state its frames show, as ``python -m jetbot_rt.train.expert`` does.

    python benchmarks/bench_expert_choices.py

- seek's search for a goal out of view: beyond 40 degrees, (-0.6, +0.2), against the old
  beyond 30 degrees, (-1, +0.3), with 150 ms motor and 100 ms camera latency;
- seek's back-off closer than 0.10 m: -0.3 against -0.8, with 66 ms of command latency;
- seek's fixed stop point against one moved out with speed (``stop_lead`` 0.15 s), and how
  far the robot coasts after the expert's first zero command: the drop in its distance to
  the goal from that tick to the closest it comes after (shown for these arms only: where a
  latency keeps older commands running, a search or a back-off can move it away instead);
- follow's pure-pursuit look-ahead: 0.15 m against 0.25 m, the median offset from the
  centre line over every step, and how far along the track the expert gets;
- follow's and avoid's slowest forward command: 0.75, what DAgger trained their students with
  (its ``--min-forward`` default replaced theirs until 2026-12-07), against their 0.8 before;
  avoid's ``clear`` (where its turn away begins): 0.27 m (the baseline) against 0.35 m before;
- the tasks' own baselines (docs/TRAINING.md, "Tasks"): avoid's expert, a constant full
  forward command on avoid and on follow;
- forward's geometry: the robot at full command from the nominal start, randomization off
  (its speed, the distance at which it touches the block, and after how many steps).

Writes expert_choices.json and .md to --out.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from versions import cpu_model, write_results

from jetbot_rt.config.sections import load_config
from jetbot_rt.tasks.follow import FollowExpert
from jetbot_rt.train.dagger_sampler import FrameState
from jetbot_rt.train.env import JetbotEnv
from jetbot_rt.train.expert import EXPERT_FRAME, task_expert

CONDITIONS = Path(__file__).parent / "seek_conditions"
SEED = 10_000


def drive(task: str, condition: str | None, settings: dict[str, float], episodes: int
          ) -> list[dict[str, Any]]:
    """Each episode's success, the robot-goal distance at the expert's first zero command
    and the least after it (goal tasks), and the median offset from the track (follow)."""
    config = load_config(CONDITIONS / f"{condition}.toml") if condition else None
    env = JetbotEnv(task, config, image_size=EXPERT_FRAME)
    constant = settings.get("constant")
    expert = None if constant else task_expert(task, settings)
    rows = []
    try:
        for i in range(episodes):
            _, info = env.reset(seed=SEED + i)
            seen = FrameState(info, env.period)
            stopped_at, closest, offsets, done = None, np.inf, [], False
            while not done:
                command = (np.asarray(constant, dtype=np.float32) if expert is None
                           else expert.label(seen.info))
                if stopped_at is None and not np.any(command) and "distance" in info:
                    stopped_at = float(info["distance"])
                _, _, terminated, truncated, info = env.step(command)
                seen.push(info)
                if stopped_at is not None:
                    closest = min(closest, float(info["distance"]))
                if "offset" in info:
                    offsets.append(float(info["offset"]))
                done = terminated or truncated
            rows.append({"success": bool(info["is_success"]),
                         "coast_m": None if stopped_at is None else stopped_at - closest,
                         "median_offset_m": statistics.median(offsets) if offsets else None,
                         "progress_m": float(info["progress"]) if "progress" in info
                         else None})
    finally:
        env.close()
    return rows


@contextmanager
def follow_lookahead(metres: float) -> Iterator[None]:
    """``FollowExpert.lookahead`` is a class constant the follow task reads every step."""
    before = FollowExpert.lookahead
    FollowExpert.lookahead = metres
    try:
        yield
    finally:
        FollowExpert.lookahead = before


ARMS: list[tuple[str, str, str, str | None, dict[str, float], float | None]] = [
    # (comparison, arm, task, condition, expert settings, follow look-ahead)
    ("search", "40 deg, (-0.6, +0.2) (now)", "seek", "latency_250ms", {}, None),
    ("search", "30 deg, (-1, +0.3) (before)", "seek", "latency_250ms",
     {"search_bearing_deg": 30.0, "search_left": -1.0, "search_right": 0.3}, None),
    ("backoff", "-0.3 (now)", "seek", "latency", {}, None),
    ("backoff", "-0.8 (before)", "seek", "latency", {"backoff": -0.8}, None),
    ("stop", "fixed stop point (now)", "seek", None, {}, None),
    ("stop", "stop_lead 0.15 s (before)", "seek", None, {"stop_lead": 0.15}, None),
    ("lookahead", "0.15 m (now)", "follow", None, {}, 0.15),
    ("lookahead", "0.25 m (before)", "follow", None, {}, 0.25),
    ("forward", "0.75 (now; every follow student's)", "follow", None, {}, 0.15),
    ("forward", "0.8 (the default before 2026-12-07, never used by DAgger)", "follow", None,
     {"min_forward": 0.8}, 0.15),
    ("forward", "0.75 (every avoid student's; here turning away at 0.27 m)", "avoid", None,
     {}, None),
    ("forward", "0.8 (never used by DAgger; here turning away at 0.27 m)", "avoid", None,
     {"min_forward": 0.8}, None),
    ("clear", "0.35 m (before 2026-12-07)", "avoid", None, {"clear": 0.35}, None),
    ("baseline", "avoid's expert", "avoid", None, {}, None),
    ("baseline", "constant forward (1, 1)", "avoid", None, {"constant": (1.0, 1.0)}, None),
    ("baseline", "constant forward (1, 1)", "follow", None, {"constant": (1.0, 1.0)}, None),
]


def forward_geometry() -> dict[str, float]:
    """forward's robot at full command from the nominal start, randomization off: its median
    speed (m/s), the least robot-block distance (the touch) and the step it is first within
    1 mm of it."""
    env = JetbotEnv("forward", randomize=False, image_size=EXPERT_FRAME)
    try:
        _, info = env.reset(seed=0, options={"start_noise": False})
        distances, speeds, done = [float(info["distance"])], [], False
        while not done:
            _, _, terminated, truncated, info = env.step(np.ones(2, dtype=np.float32))
            distances.append(float(info["distance"]))
            speeds.append(float(info["speed"]))
            done = terminated or truncated
    finally:
        env.close()
    touch = min(distances)
    return {"start_distance_m": round(distances[0], 4),
            "median_speed_m_s": round(statistics.median(speeds[30:]), 4),
            "touch_distance_m": round(touch, 4),
            "touch_step": next(i for i, d in enumerate(distances) if d < touch + 0.001),
            "episode_steps": len(distances) - 1}


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    coasts = sorted(r["coast_m"] for r in rows if r["coast_m"] is not None)
    offsets = [r["median_offset_m"] for r in rows if r["median_offset_m"] is not None]
    progress = sorted(r["progress_m"] for r in rows if r["progress_m"] is not None)
    return {"episodes": len(rows), "successes": sum(r["success"] for r in rows),
            "coast_cm": None if not coasts else {
                "min": round(100 * coasts[0], 2),
                "median": round(100 * statistics.median(coasts), 2),
                "p95": round(100 * float(np.percentile(coasts, 95)), 2),
                "max": round(100 * coasts[-1], 2)},
            "median_offset_cm": round(100 * statistics.median(offsets), 2) if offsets else None,
            "progress_m": None if not progress else {
                "min": round(progress[0], 2), "median": round(statistics.median(progress), 2),
                "max": round(progress[-1], 2)}}


def markdown(result: dict[str, Any]) -> str:
    lines = ["# The experts' design choices against what they replaced", "",
             f"Machine: {result['cpu']}, {result['cores']} cores, {result['date']}. Command: "
             f"`{result['command']}`. Each expert on the episodes of seeds {SEED}+, acting on "
             "the state its frames show; the condition files are in "
             "`benchmarks/seek_conditions/` (none: the task's randomization).", "",
             "| comparison | arm | task | condition | success | coast after the first zero "
             "command, cm (min / median / p95 / max) | median offset from the centre line | "
             "along the track, m (min / median / max) |",
             # the coast only where the stop is compared (see the docstring)
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in result["arms"]:
        coast = row["coast_cm"] if row["comparison"] == "stop" else None
        lines.append(
            f"| {row['comparison']} | {row['arm']} | {row['task']} | "
            f"{row['condition'] or 'randomized'} | {row['successes']} / {row['episodes']} | "
            + (f"{coast['min']} / {coast['median']} / {coast['p95']} / {coast['max']}"
               if coast else "") + " | "
            + (f"{row['median_offset_cm']} cm" if row["median_offset_cm"] is not None else "")
            + " | " + (" / ".join(str(row["progress_m"][k]) for k in ("min", "median", "max"))
                       if row.get("progress_m") else "") + " |")
    geometry = result.get("forward_geometry")
    if geometry:
        lines += ["", "forward at full command from the nominal start, randomization off: "
                  f"{geometry['start_distance_m']} m from the block at the start, "
                  f"{geometry['median_speed_m_s']} m/s (median after the first second), "
                  f"touching it at {geometry['touch_distance_m']} m (robot base to block) "
                  f"from step {geometry['touch_step']} of {geometry['episode_steps']}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()

    arms = []
    for comparison, arm, task, condition, settings, lookahead in ARMS:
        began = time.perf_counter()
        with follow_lookahead(lookahead if lookahead is not None else FollowExpert.lookahead):
            rows = drive(task, condition, settings, args.episodes)
        arms.append({"comparison": comparison, "arm": arm, "task": task,
                     "condition": condition, "settings": settings, "lookahead": lookahead,
                     **summary(rows), "wall_s": round(time.perf_counter() - began, 1)})
        print(arms[-1], flush=True)
    result = {"cpu": cpu_model(), "cores": os.cpu_count(), "date": time.strftime("%Y-%m-%d"),
              "episodes": args.episodes,
              "command": "python benchmarks/bench_expert_choices.py " + " ".join(sys.argv[1:]),
              "arms": arms, "forward_geometry": forward_geometry()}
    write_results(args.out, "expert_choices", result, markdown(result))


if __name__ == "__main__":
    main()
