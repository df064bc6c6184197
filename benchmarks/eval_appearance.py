"""Evaluate a policy on the held-out appearance conditions, with the blind baselines beside.

Each condition is a TOML file (default: benchmarks/appearance_conditions/*.toml, looks that
``[randomize] appearance`` never draws in training: ``jetbot_rt.sim.look_draws.held_out``
says why for each). For every condition it runs ``jetbot-train eval`` three times on the same
seeded episodes: the policy, ``--ablate blank`` (a constant grey frame) and
``--ablate constant-forward`` (mu = [1, 1], no network). Writes OUT/<condition>-<run>.json
and OUT/summary.md (command, machine, date, the table) and prints the table.

Run:
  .venv/bin/python benchmarks/eval_appearance.py --task seek --episodes 30 \\
      --out benchmarks/results/appearance_before
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RUNS = {"policy": [], "blank": ["--ablate", "blank"],
        "constant": ["--ablate", "constant-forward"]}


def reason(path: Path) -> str:
    """Why the condition is held out from the default training draws."""
    from jetbot_rt.config.sections import Config, load_config
    from jetbot_rt.sim.look_draws import held_out

    config = load_config(path)
    return held_out(config.sim, Config().randomize) or "NOT held out"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default=None, help="ONNX file (default: the bundled one)")
    parser.add_argument("--task", default="seek")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument("--seed", type=int, default=30000)
    parser.add_argument("--conditions", type=Path, default=HERE / "appearance_conditions")
    parser.add_argument("--only", nargs="*", default=None, help="condition names to run")
    parser.add_argument("--no-baselines", action="store_true")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--resume", action="store_true",
                        help="keep the results already in --out, run only the missing ones")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    train = [str(Path(sys.executable).with_name("jetbot-train"))]
    files = sorted(args.conditions.glob("*.toml"))
    if args.only:
        files = [f for f in files if f.stem in args.only]
    runs = {"policy": []} if args.no_baselines else RUNS
    rows = []
    for path in files:
        row = {"condition": path.stem, "held_out": reason(path)}
        for run, extra in runs.items():
            done_file = args.out / f"{path.stem}-{run}.json"
            if args.resume and done_file.exists():  # an earlier invocation's, same episodes
                row[run] = json.loads(done_file.read_text())["success_rate"]
                continue
            command = [*train, "eval", "--task", args.task, "--episodes", str(args.episodes),
                       "--num-envs", str(args.num_envs), "--seed", str(args.seed),
                       "--config", str(path), "--json", "--no-progress", *extra]
            if args.policy:
                command += ["--policy", args.policy]
            done = subprocess.run(command, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                print(f"{path.stem} {run}: exit {done.returncode}: {done.stderr.strip()}",
                      file=sys.stderr)
                return 1
            done_file.write_text(done.stdout)
            row[run] = json.loads(done.stdout)["success_rate"]
        rows.append(row)
        print(row, flush=True)
    header = "| condition | held out because | " + " | ".join(runs) + " |"
    lines = [
        f"# Appearance conditions: {args.task}, {args.episodes} episodes each "
        f"(seeds {args.seed}..{args.seed + args.episodes - 1})",
        "",
        f"Command: `{' '.join(shlex.quote(a) for a in sys.argv)}`  ",
        f"Policy: {args.policy or 'the bundled policy of the task'}  ",
        f"Machine: {platform.node()}, {os.cpu_count()} cores, {platform.platform()}  ",
        f"Date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC",
        "",
        header,
        "| --- | --- | " + " | ".join("---" for _ in runs) + " |",
    ]
    for row in rows:
        cells = " | ".join(f"{100 * row[r]:.0f} %" for r in runs)
        lines.append(f"| {row['condition']} | {row['held_out']} | {cells} |")
    (args.out / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
