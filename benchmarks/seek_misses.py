"""Why a seek policy missed: replays the episodes ``jetbot-train eval`` reported as misses
(the seeds of its ``--json`` output absent from ``successes``) and sorts each by where it
ended (``tasks/seek.py``: success is within ``success_distance`` of the goal, stopped, the
block pushed less than ``max_block_shift``):

- "pushed": the goal block pushed too far (the episode's failure);
- "at the goal, moving": within ``success_distance`` but not stopped at the end;
- "stayed at the start": never 0.2 m from where it started, at any step;
- "at a distractor": ended nearer a green or blue block than the goal, within 0.25 m of it
  (it drove to the wrong block: a seeing miss);
- "near the goal": ended within 0.4 m of the goal (stopped short or wandered near it);
- "elsewhere": anywhere else (lost, circling, out of the area).

Each line also gives the policy's mean command (left, right) over the episode, its last
command, the episode's drawn dead-band and the lift the robot applied (``[actions] deadband``,
drawn on a calibrated robot), where there is one: a robot stopped short of the goal while
commanding a crawl below its unlifted dead-band stalled, it did not choose to stop.

    python benchmarks/seek_misses.py --policy P.onnx --eval heldout.json [--episodes N] [--config C]

Prints one line a miss and the counts; the replay uses the evaluation's environment, so a
miss that does not fail again is printed as "passed now".
"""

from __future__ import annotations

import math

import numpy as np
from replay_misses import Episode, main

from jetbot_rt.tasks.scene import Block

AT_DISTRACTOR = 0.25
NEAR_GOAL = 0.4
LEFT_THE_START = 0.2


def kind(info: dict, task, distractor: float, farthest: float) -> str:
    if info["is_success"]:
        return "passed now"
    if info["failed"]:
        return "pushed"
    if info["distance"] < task.success_distance:
        return "at the goal, moving"
    if farthest < LEFT_THE_START:  # before "near the goal": a goal may start 0.35 m away
        return "stayed at the start"
    if distractor < min(AT_DISTRACTOR, info["distance"]):
        return "at a distractor"
    if info["distance"] < NEAR_GOAL:
        return "near the goal"
    return "elsewhere"


def sort(env, info: dict, episode: Episode) -> tuple[str, str]:
    robot = np.asarray(info["pose"][:2], dtype=float)
    others = [p.xy for p in env.unwrapped.scene.pieces
              if isinstance(p, Block) and p.color in ("green", "blue")]
    distractor = min((float(np.linalg.norm(robot - np.asarray(xy))) for xy in others),
                     default=math.inf)
    left, right = episode.mean_command
    last_left, last_right = episode.last_command
    drawn = env.unwrapped.sim_params
    lifted = env.unwrapped.pipeline.deadband
    lift = f", lift {lifted:.2f}" if lifted > 0 else ""
    return (kind(info, env.unwrapped.task, distractor, episode.farthest),
            f"goal {info['distance']:.2f} m, nearest distractor {distractor:.2f} m, at most "
            f"{episode.farthest:.2f} m from the start, speed {info['speed']:.3f} m/s, mean "
            f"command ({left:.2f}, {right:.2f}), last ({last_left:.2f}, {last_right:.2f}), "
            f"dead-band {drawn.get('deadband', 0.0):.2f}{lift}")


if __name__ == "__main__":
    main("seek", __doc__, sort)
