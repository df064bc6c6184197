"""Why an avoid policy missed: replays the episodes ``jetbot-train eval`` reported as misses
(the seeds of its ``--json`` output absent from ``successes``) and sorts each into the ways
avoid fails (``tasks/avoid.py``): a touch, a circle (``min_path`` driven but never
``min_reach`` from the start) or a short drive (less than ``min_path``).

    python benchmarks/avoid_misses.py --policy P.onnx --eval randomized.json [--episodes N]

Prints one line a miss and the counts; the replay uses the evaluation's own episode code
and ablation, so a miss that does not fail again is printed as "passed now".
"""

from __future__ import annotations

from replay_misses import Episode, main


def kind(info: dict, task) -> str:
    if info["is_success"]:
        return "passed now"
    if info["failed"]:
        return "touch"
    if info["path_length"] >= task.min_path:
        return "circle"
    return "short"


def sort(env, info: dict, episode: Episode) -> tuple[str, str]:
    return (kind(info, env.unwrapped.task),
            f"path {info['path_length']:.2f} m, reach {info['reach']:.2f} m")


if __name__ == "__main__":
    main("avoid", __doc__, sort)
