"""What the imperfections and the randomization cost an env step, against the ideal sim in
the same run (interleaved rounds, best round of each). Writes benchmarks/results/
imperfections.json and .md. Run: .venv/bin/python benchmarks/bench_imperfections.py"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from versions import stamp

from jetbot_rt.config.sections import from_dict
from jetbot_rt.train.env import JetbotEnv

RESULTS = Path(__file__).resolve().parent / "results"
STEPS, ROUNDS = 150, 5
CASES = {
    "ideal": {},
    "dc motor + latency": {"sim": {"stall_torque": 0.078, "latency": 0.05, "deadband": 0.05}},
    "camera latency": {"sim": {"camera_latency": 0.07}},
    "sensor effects": {"sim": {"image_noise": 0.02, "image_blur": 0.005, "image_contrast": 0.9}},
    "randomized": {"randomize": {"enabled": True}, "actions": {"max_speed": 0.4}},
}


def steps_per_s(env: JetbotEnv) -> float:
    env.reset(seed=0)
    action = np.array([0.6, 0.4])
    start = time.perf_counter()
    for _ in range(STEPS):
        env.step(action)
    return STEPS / (time.perf_counter() - start)


def main() -> None:
    envs = {name: JetbotEnv("forward", from_dict(data)) for name, data in CASES.items()}
    best = {name: 0.0 for name in CASES}
    try:
        for _ in range(ROUNDS):
            for name, env in envs.items():
                best[name] = max(best[name], steps_per_s(env))
    finally:
        for env in envs.values():
            env.close()
    result = {
        "image_size": list(envs["ideal"].observation_space.shape[:2]),
        "lens": from_dict({}).sim.lens,
        "steps_per_s": {k: round(v, 1) for k, v in best.items()},
        "ratio_to_ideal": {k: round(v / best["ideal"], 3) for k, v in best.items()},
        "load_avg_1min": os.getloadavg()[0],
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "imperfections.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    lines = ["| case | env steps/s | vs ideal |", "| --- | --- | --- |"]
    lines += [f"| {k} | {result['steps_per_s'][k]} | {result['ratio_to_ideal'][k]} |"
              for k in CASES]
    lines.append(f"\nImage {result['image_size']}, {result['lens']} lens, best of {ROUNDS} "
                 f"interleaved rounds of {STEPS} steps; 1-min load average at the end "
                 f"{result['load_avg_1min']:.1f}.")
    (RESULTS / "imperfections.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
