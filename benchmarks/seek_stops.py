"""Where a seek policy stops: replays the successes of a ``jetbot-train eval --json`` output
and gives the distance from the robot's axle midpoint to the goal's centre at which each
ended (success needs it below ``success_distance``, 0.15 m, the robot stopped and the block
not pushed), with its quartiles and how many stopped within 1 cm of the threshold. Stops
crowding the threshold miss by a centimetre where a scene looks a little different or a
wheel is weak (``benchmarks/results/ppo_15min_lift_h100/``).

    python benchmarks/seek_stops.py --policy P.onnx --eval E.json [--config C] [--episodes N]
"""

from __future__ import annotations

import numpy as np
from replay_misses import open_replay, replay

NEAR_THE_THRESHOLD = 0.01
"""m; a stop this close to ``success_distance`` (or closer) counts as crowding it."""


def summary(distances: list[float], threshold: float, failed_now: int = 0) -> str:
    """The quartiles of the successes' final distances, how many crowd ``threshold`` and how
    many of the evaluation's successes failed when replayed (a replay with another config
    than the evaluation's, or another machine's numerics)."""
    failed = f"; {failed_now} failed now" if failed_now else ""
    if not distances:
        return "no successes" + failed
    low, q1, median, q3, high = np.quantile(distances, [0.0, 0.25, 0.5, 0.75, 1.0])
    crowding = sum(d >= threshold - NEAR_THE_THRESHOLD for d in distances)
    return (f"{len(distances)} successes: final distance min {low:.3f}, quartiles {q1:.3f} / "
            f"{median:.3f} / {q3:.3f}, max {high:.3f} m; {crowding} within "
            f"{NEAR_THE_THRESHOLD * 100:g} cm of {threshold:g} m{failed}")


def main() -> None:
    run = open_replay("seek", __doc__)
    threshold = float(run.env.unwrapped.task.success_distance)
    distances: list[float] = []
    failed_now = 0
    try:
        for seed in sorted(set(run.seeds) & run.successes):
            info, _ = replay(run.env, run.policy, seed)
            if not info["is_success"]:
                print(f"{seed}: failed now", flush=True)
                failed_now += 1
                continue
            distances.append(float(info["distance"]))
            print(f"{seed}: {info['distance']:.3f} m", flush=True)
    finally:
        run.env.close()
    print(summary(distances, threshold, failed_now))


if __name__ == "__main__":
    main()
