"""The loop benchmark (bench_loop.py), old against new in the same run: a baseline revision is
checked out into a temporary git worktree, and each tree's own bench_loop.py runs on its own
code, alternating, ``--rounds`` times. Writes benchmarks/results/loop_ab.json and loop_ab.md.

    python benchmarks/compare_loop.py --baseline REV [--seconds 10] [--trials 30] [--rounds 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from versions import stamp

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"


def bench(tree: Path, args: argparse.Namespace) -> dict:
    """One bench_loop.py run on ``tree``'s code; ``tree``'s recorded loop.json/loop.md are left
    as they were (these short runs are comparisons, not the recorded figures)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    recorded = {name: (tree / "benchmarks" / "results" / name) for name in ("loop.json",
                                                                            "loop.md")}
    kept = {name: path.read_bytes() for name, path in recorded.items() if path.exists()}
    try:
        return _bench(tree, env, args)
    finally:
        for name, data in kept.items():
            recorded[name].write_bytes(data)


def _bench(tree: Path, env: dict[str, str], args: argparse.Namespace) -> dict:
    result_file = tree / "benchmarks" / "results" / "loop.json"
    subprocess.run(
        [sys.executable, str(tree / "benchmarks" / "bench_loop.py"), "--seconds",
         str(args.seconds), "--trials", str(args.trials), "--overhead-ticks",
         str(args.overhead_ticks)],
        check=True, env=env, cwd=tree, stdout=subprocess.DEVNULL,
    )
    return json.loads(result_file.read_text())


def figures(result: dict) -> dict[str, float]:
    out = {}
    for run, floor in zip(result["jitter"], result["sleep_baseline"], strict=True):
        out[f"jitter p99 @ {run['rate_hz']:g} Hz (ms)"] = run["start_jitter_ms"]["p99"]
        out[f"bare sleep p99 @ {floor['rate_hz']:g} Hz, same run (ms)"] = \
            floor["start_jitter_ms"]["p99"]
    out["overhead p50 (ms)"] = result["overhead"]["overhead_ms"]["p50"]
    out["overhead p99 (ms)"] = result["overhead"]["overhead_ms"]["p99"]
    out["watchdog stop after timeout p99 (ms)"] = \
        result["watchdog"]["stop_after_timeout_ms"]["p99"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", required=True, help="git revision to compare against")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--trials", type=int, default=30)
    parser.add_argument("--overhead-ticks", type=int, default=3000)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True, check=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "baseline"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "-q", "--detach", str(base),
                        args.baseline], check=True)
        try:
            runs: dict[str, list[dict[str, float]]] = {"baseline": [], "new": []}
            for _ in range(args.rounds):
                runs["baseline"].append(figures(bench(base, args)))
                runs["new"].append(figures(bench(REPO, args)))
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(base)],
                           check=False)
    load = os.getloadavg()
    best = {side: {key: min(r[key] for r in rs) for key in rs[0]} for side, rs in runs.items()}
    result = {"baseline": args.baseline, "new": head, "rounds": args.rounds,
              "seconds": args.seconds, "trials": args.trials,
              "loadavg_after": [round(x, 2) for x in load], "runs": runs, "best": best}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "loop_ab.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    lines = [f"Loop benchmark, baseline {args.baseline} vs {head}, alternating, {args.rounds} "
             f"rounds (best of rounds); load average after: {result['loadavg_after']}", "",
             "| measure | baseline | new | new/baseline |", "|---|---|---|---|"]
    for key in best["baseline"]:
        old, new = best["baseline"][key], best["new"][key]
        ratio = f"x{new / old:.2f}" if old else "-"
        lines.append(f"| {key} | {old} | {new} | {ratio} |")
    (RESULTS / "loop_ab.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
