"""Learning curves of the forward task: PPO's update recipe now (4 epochs x 2 minibatches)
against the old one (8 x 4), both at 56x56, and the bundled policy's run (8 x 4 at 224x224).

    python benchmarks/plot_recipe_curves.py   # reads and writes benchmarks/results/

The two 56x56 runs: ``jetbot-train train --task forward --timesteps 40000 --num-envs 2
--seed 1`` with and without ``--update-epochs 8 --num-minibatches 4``; their metrics.csv
copied to recipe-now.csv and recipe-old.csv; recipe-stem4.csv is the same command with
forward's network since then (first layer 6x6, stride 4) and the learner computing every
step's actions (``--sample-in-workers false``), recipe-sampler.csv the command as it is now
(the policy run in the env workers).
"""

from __future__ import annotations

import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

RESULTS = Path(__file__).resolve().parent / "results"
RUNS = (("recipe-sampler.csv", "56x56, 4 x 2, 6x6 stride 4, policy in the workers (default now)"),
        ("recipe-stem4.csv", "56x56, 4 x 2, first layer 6x6 stride 4, learner per step"),
        ("recipe-now.csv", "56x56, 4 epochs x 2 minibatches, first layer 5x5 stride 2"),
        ("recipe-old.csv", "56x56, 8 epochs x 4 minibatches (old)"),
        ("train.csv", "224x224, 8 x 4: the bundled policy's run"))


def main() -> None:
    fig, (ax_succ, ax_dist) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for name, label in RUNS:
        with (RESULTS / name).open() as handle:
            rows = [r for r in csv.DictReader(handle) if r["success_rate"]]
        steps = [int(r["global_step"]) for r in rows]
        ax_succ.plot(steps, [float(r["success_rate"]) for r in rows], label=label)
        ax_dist.plot(steps, [float(r["mean_final_distance"]) for r in rows], label=label)
    ax_succ.set_ylabel("training success (last 20 episodes)")
    ax_succ.set_ylim(-0.05, 1.05)
    ax_succ.legend(loc="lower right", fontsize=8)
    ax_dist.axhline(0.15, color="gray", linestyle=":", label="success distance")
    ax_dist.set_ylabel("mean final distance (m)")
    ax_dist.set_xlabel("environment steps")
    fig.suptitle("forward task, seed 1: PPO update recipes")
    fig.tight_layout()
    fig.savefig(RESULTS / "recipe_curves.png", dpi=100)


if __name__ == "__main__":
    main()
