"""PPO runs' training success against wall time, from each run's metrics.csv in one results
folder (commands in its README.md). By default the two runs of
``benchmarks/results/ppo_critic_h200/``: the critic on the simulator's state (``--critic
state``) and on the image (the default).

    python benchmarks/plot_ppo_critic.py   # writes benchmarks/results/ppo_critic_h200/curves.png
    python benchmarks/plot_ppo_critic.py --dir benchmarks/results/ppo_lift_h200 \\
        --run plain "plain robot" --run lift "calibrated robot (lift)" --envs 8
    python benchmarks/plot_ppo_critic.py --dir benchmarks/results/ppo_15min_h100 \\
        --run run "--target-kl 0.02 --augment 0.1" --host "H100 host, resumed at 481 s"
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

RESULTS = Path(__file__).resolve().parent / "results"
SMOOTH = 25
RUNS = (("state", "--critic state (asymmetric)"), ("image", "--critic image (default)"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dir", type=Path, default=RESULTS / "ppo_critic_h200")
    parser.add_argument("--run", nargs=2, action="append", metavar=("FOLDER", "LABEL"),
                        help="a run's folder (holding metrics.csv) in --dir, and its label")
    parser.add_argument("--envs", type=int, default=16, help="env workers of each run")
    parser.add_argument("--host", default="H200 host", help="the machine, for the title")
    args = parser.parse_args()
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, label in args.run or RUNS:
        with (args.dir / name / "metrics.csv").open() as handle:
            rows = [r for r in csv.DictReader(handle) if r["success_rate"] not in ("", "nan")]
        wall = [float(r["wall_s"]) for r in rows]
        success = [float(r["success_rate"]) for r in rows]
        ax.plot(wall, success, linewidth=0.5, alpha=0.35)
        windows = [success[max(0, i - SMOOTH + 1):i + 1] for i in range(len(success))]
        smooth = [sum(w) / len(w) for w in windows]
        ax.plot(wall, smooth, label=f"{label}, mean of {SMOOTH} updates",
                color=ax.lines[-1].get_color(), linewidth=1.5)
    ax.set_xlabel(f"wall time (s), {args.envs} env workers, learner on the GPU")
    ax.set_ylabel("training success (rollout episodes)")
    ax.set_ylim(0, 1)
    ax.axhline(0.9, color="grey", linestyle=":", linewidth=0.8)
    ax.legend(loc="lower right")
    ax.set_title(f"PPO on seek from pixels, {args.host}")
    fig.tight_layout()
    fig.savefig(args.dir / "curves.png", dpi=100)


if __name__ == "__main__":
    main()
