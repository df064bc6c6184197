"""PPO on seek from pixels with the critic on the simulator's state (``--critic state``) and on
the image (the default), training success against wall time, from the two runs' metrics.csv
in ``benchmarks/results/ppo_critic_h200/`` (commands in its README.md).

    python benchmarks/plot_ppo_critic.py   # writes benchmarks/results/ppo_critic_h200/curves.png
"""

from __future__ import annotations

import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

HERE = Path(__file__).resolve().parent / "results" / "ppo_critic_h200"
SMOOTH = 25
RUNS = (("state", "--critic state (asymmetric)"), ("image", "--critic image (default)"))


def main() -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, label in RUNS:
        with (HERE / name / "metrics.csv").open() as handle:
            rows = [r for r in csv.DictReader(handle) if r["success_rate"] not in ("", "nan")]
        wall = [float(r["wall_s"]) for r in rows]
        success = [float(r["success_rate"]) for r in rows]
        ax.plot(wall, success, linewidth=0.5, alpha=0.35)
        windows = [success[max(0, i - SMOOTH + 1):i + 1] for i in range(len(success))]
        smooth = [sum(w) / len(w) for w in windows]
        ax.plot(wall, smooth, label=f"{label}, mean of {SMOOTH} updates",
                color=ax.lines[-1].get_color(), linewidth=1.5)
    ax.set_xlabel("wall time (s), 16 env workers, learner on the GPU")
    ax.set_ylabel("training success (rollout episodes)")
    ax.set_ylim(0, 1)
    ax.axhline(0.9, color="grey", linestyle=":", linewidth=0.8)
    ax.legend(loc="upper left")
    ax.set_title("PPO on seek from pixels, H200 host")
    fig.tight_layout()
    fig.savefig(HERE / "curves.png", dpi=100)


if __name__ == "__main__":
    main()
