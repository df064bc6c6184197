"""The seed's real failure, drawn: the bundled forward policy and the bundled seek policy on
the forward task's scene (a red block 0.9 m straight ahead, nominal start), with the right
wheel 15 % weak (``[sim] wheel_gain = [1.0, 0.85]``), from above. Writes
docs/images/weak_wheel.png and its legend's figures, with the versions, to
benchmarks/results/weak_wheel.json. Run: .venv/bin/python benchmarks/plot_weak_wheel.py"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from versions import stamp

from jetbot_rt.config.sections import from_dict
from jetbot_rt.runtime.policy import bundled_policy_path
from jetbot_rt.train.env import JetbotEnv
from jetbot_rt.train.evaluate import load_policy

OUT = Path(__file__).resolve().parent.parent / "docs" / "images" / "weak_wheel.png"
RESULTS = Path(__file__).resolve().parent / "results" / "weak_wheel.json"
WEAK = [1.0, 0.85]


def trajectory(policy_task: str, gain: list[float]) -> tuple[np.ndarray, dict]:
    config = from_dict({"sim": {"wheel_gain": gain}})
    policy = load_policy(bundled_policy_path(policy_task), config)
    env = JetbotEnv("forward", config, randomize=False, model_max_speed=policy.max_speed,
                    image_size=(policy.spec.width, policy.spec.height))
    try:
        obs, info = env.reset(seed=0, options={"start_noise": False})
        poses = [info["pose"][:2]]
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(policy.infer(obs))
            poses.append(info["pose"][:2])
            done = terminated or truncated
    finally:
        env.close()
    return np.array(poses), info


def main() -> None:
    fig, ax = plt.subplots(figsize=(7, 5))
    runs = []
    for task, gain, style in [("forward", [1.0, 1.0], ":"), ("forward", WEAK, "-"),
                              ("seek", WEAK, "-")]:
        path, info = trajectory(task, gain)
        label = (f"{task}.onnx, wheel_gain {gain}: final distance {info['distance']:.2f} m, "
                 f"{'success' if info['distance'] < 0.15 else 'miss'}")
        ax.plot(path[:, 0], path[:, 1], style, lw=2, label=label)
        runs.append({"policy": f"{task}.onnx", "wheel_gain": gain,
                     "final_distance_m": round(float(info["distance"]), 3),
                     "success": bool(info["distance"] < 0.15)})
    ax.add_patch(plt.Rectangle((0.275, -0.025), 0.05, 0.05, color="red"))
    ax.add_patch(plt.Circle((0.3, 0.0), 0.15, fill=False, ls="--", color="grey"))
    ax.plot([-0.6], [0.0], "ko")
    ax.set_aspect("equal")
    ax.set_xlim(-0.7, 0.6)
    ax.set_ylim(-0.6, 0.2)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Right wheel 15 % weak, the forward task's scene (start: black dot; "
                 "success circle 0.15 m)", fontsize=9)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.15))
    fig.tight_layout()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=100, bbox_inches="tight")
    RESULTS.write_text(json.dumps(stamp({
        "command": "python benchmarks/plot_weak_wheel.py", "scene": "forward, seed 0, "
        "nominal start, randomization off", "runs": runs}), indent=2) + "\n")
    print(f"wrote {OUT} and {RESULTS}")


if __name__ == "__main__":
    main()
