"""Why an avoid policy missed: replays the episodes ``jetbot-train eval`` reported as misses
(the seeds of its ``--json`` output absent from ``successes``) and sorts each into the ways
avoid fails (``tasks/avoid.py``): a touch, a circle (``min_path`` driven but never
``min_reach`` from the start) or a short drive (less than ``min_path``).

    python benchmarks/avoid_misses.py --policy P.onnx --eval randomized.json [--episodes N]

Prints one line a miss and the counts; the replay uses the evaluation's own episode code
(``evaluate.run_episode``), so a miss that does not fail again is printed as "passed now".
"""

from __future__ import annotations

import argparse

from jetbot_rt.config.safe_file import read_json
from jetbot_rt.config.sections import load_config
from jetbot_rt.train.env import JetbotEnv
from jetbot_rt.train.evaluate import load_policy


def kind(info: dict, task) -> str:
    if info["is_success"]:
        return "passed now"
    if info["failed"]:
        return "touch"
    if info["path_length"] >= task.min_path:
        return "circle"
    return "short"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", required=True)
    parser.add_argument("--eval", required=True, help="an eval --json output of this policy")
    parser.add_argument("--episodes", type=int, default=100, help="the evaluation's count")
    parser.add_argument("--config", default=None)
    args = parser.parse_args()
    report = read_json(args.eval, "evaluation", 1 << 20)
    first = report["seed"]
    misses = sorted(set(range(first, first + args.episodes)) - set(report["successes"]))
    config = load_config(args.config)
    policy = load_policy(args.policy, config)
    env = JetbotEnv("avoid", config, model_max_speed=policy.max_speed,
                    image_size=(policy.spec.width, policy.spec.height))
    task = env.unwrapped.task
    counts: dict[str, int] = {}
    try:
        for seed in misses:
            obs, info = env.reset(seed=seed)
            done = False
            while not done:
                obs, _, terminated, truncated, info = env.step(policy.infer(obs))
                done = terminated or truncated
            found = kind(info, task)
            counts[found] = counts.get(found, 0) + 1
            print(f"{seed}: {found} (path {info['path_length']:.2f} m, reach "
                  f"{info['reach']:.2f} m)", flush=True)
    finally:
        env.close()
    print(", ".join(f"{n} {k}" for k, n in sorted(counts.items())))


if __name__ == "__main__":
    main()
