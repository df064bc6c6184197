"""Which randomized draws a policy fails on: for an evaluation's episodes (the seeds of a
``jetbot-train eval --json`` output, randomized as the evaluation drew them) it re-draws each
episode's ``[sim]`` (a reset, no driving) and tabulates success by each drawn value: numbers
by quartile (a list such as ``wheel_gain`` by its smallest element), names and flags by
value. Each factor's gap between its best and worst bin comes with its chance: how often
shuffling the successes over the same episodes gives a gap as large. Sorted by that chance.

    python benchmarks/success_by_draw.py --task seek --eval heldout.json [--episodes N] [--top K]

The draws are the env's own (``JetbotEnv.reset(seed)`` -> ``sim_params``), so the table
describes the same episodes the evaluation ran, with the default config unless ``--config``.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
from eval_report import evaluation_arguments, read_evaluation

from jetbot_rt.config.sections import load_config
from jetbot_rt.train.env import JetbotEnv

SKIP = ("seed", "look_seed")
"""Per-episode noise seeds: no factor."""
MIN_BIN = 5
FEW = 6
SHUFFLES = 2000


def scalar(value: Any) -> float | str | None:
    """A draw as one number or a name; a list of numbers by its smallest element (a weak
    wheel's gain, a colour's darkest channel); ``None`` (a piece left out) as "none"."""
    if value is None:
        return "none"
    if isinstance(value, (bool, str)):
        return str(value)
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, list) and value and all(isinstance(v, (int, float)) for v in value):
        return float(min(value))
    return None


def bins(values: list[float | str]) -> tuple[list[str], np.ndarray]:
    """The bins' labels and each episode's bin: quartiles of numbers, or one bin a value (a
    name, or a number with at most ``FEW`` values: a count of lamps)."""
    if all(isinstance(v, float) for v in values) and len(set(values)) > FEW:
        x = np.asarray(values, dtype=float)
        edges = np.unique(np.quantile(x, [0.0, 0.25, 0.5, 0.75, 1.0]))
        which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
        return [f"{edges[i]:.3g}-{edges[i + 1]:.3g}" for i in range(len(edges) - 1)], which
    labels = [str(v) for v in sorted(set(values), key=lambda v: (isinstance(v, str), v))]
    return labels, np.array([labels.index(str(v)) for v in values])


def gap(which: np.ndarray, passed: np.ndarray, size: int) -> float:
    """The best bin's success rate less the worst's, over bins of at least ``MIN_BIN``."""
    counts = np.bincount(which, minlength=size)
    wins = np.bincount(which, weights=passed, minlength=size)
    rates = wins[counts >= MIN_BIN] / counts[counts >= MIN_BIN]
    return float(rates.max() - rates.min()) if len(rates) > 1 else 0.0


def chance(which: np.ndarray, passed: np.ndarray, size: int, observed: float,
           rng: np.random.Generator) -> float:
    """How often chance alone makes such a gap on these episodes: of ``SHUFFLES`` random
    relabellings of success, the share with a gap at least as large (counting the observed
    one, so never 0)."""
    hits = sum(gap(which, rng.permutation(passed), size) >= observed for _ in range(SHUFFLES))
    return (hits + 1) / (SHUFFLES + 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", required=True)
    evaluation_arguments(parser, "an eval --json output")
    parser.add_argument("--top", type=int, default=8, help="factors to print")
    args = parser.parse_args()
    _, seeds, successes = read_evaluation(args.eval, args.episodes)
    first, count = seeds.start, len(seeds)
    passed = [seed in successes for seed in seeds]
    env = JetbotEnv(args.task, load_config(args.config))
    draws: dict[str, list[Any]] = {}
    lists: set[str] = set()  # factors drawn as lists, named by their smallest element
    try:
        for seed in seeds:
            env.reset(seed=seed)
            for name, value in env.unwrapped.sim_params.items():
                draws.setdefault(name, []).append(scalar(value))
                if isinstance(value, list):
                    lists.add(name)
    finally:
        env.close()
    ok = np.asarray(passed, dtype=float)
    rng = np.random.default_rng(0)
    table = []
    for name, values in draws.items():
        if name in SKIP or any(v is None for v in values) or len({*map(str, values)}) < 2:
            continue
        if "none" in values and any(isinstance(v, float) for v in values):
            values = ["none" if v == "none" else "drawn" for v in values]  # a piece or none
        elif name in lists:
            name = f"{name} (smallest)"
        labels, which = bins(values)
        observed = gap(which, ok, len(labels))
        cells = ", ".join(f"{label}: {int(ok[which == i].sum())}/{int(np.sum(which == i))}"
                          for i, label in enumerate(labels) if np.any(which == i))
        table.append((observed, name, chance(which, ok, len(labels), observed, rng), cells))
    table.sort(key=lambda row: (row[2], -row[0]))
    print(f"{int(ok.sum())} / {count} episodes passed (seeds {first}..{first + count - 1}); "
          f"{len(table)} factors, so a chance below {0.05 / max(len(table), 1):.4f} is "
          "unlikely to be luck (Bonferroni, 5 %)")
    print("| factor | best - worst bin | chance | success by bin (successes / episodes) |\n"
          "| --- | --- | --- | --- |")
    for observed, name, p, cells in table[:args.top]:
        print(f"| {name} | {100 * observed:.0f} pts | {p:.4f} | {cells} |")


if __name__ == "__main__":
    main()
