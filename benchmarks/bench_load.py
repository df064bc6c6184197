"""Both cores saturated while the real backend drives at 30 Hz (the fault matrix's load case,
run for 30 s instead of the suite's 8 s): whether the loop keeps its schedule, how many
deadlines it skips, how late it starts, or whether its watchdog stops it.

    python benchmarks/bench_load.py [--seconds 30] [--runs 3]

Runs tests/test_fault_load.py's case through pytest (the same code, a longer load) and writes
benchmarks/results/load.{json,md} with the machine's load average before each run."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from versions import stamp

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
CASE = "tests/test_fault_load.py::test_two_busy_cores_the_loop_keeps_its_schedule_or_stops_safely"


def run_once(seconds: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        figures = Path(tmp) / "figures.jsonl"
        env = {**os.environ, "JETBOT_RT_LOAD_S": str(seconds),
               "JETBOT_RT_FAULT_FIGURES": str(figures)}
        load_before = os.getloadavg()[0]
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                               CASE], cwd=ROOT, env=env, capture_output=True, text=True)
        row = json.loads(figures.read_text().splitlines()[-1]) if figures.exists() else {}
        return {"load_before": round(load_before, 2), "pytest_rc": done.returncode, **row}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    rows = [run_once(args.seconds) for _ in range(args.runs)]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "load.json").write_text(json.dumps(stamp(rows), indent=1) + "\n")
    keys = ["load_before", "exit_code", "ticks_under_load", "overruns", "tick_ms_p99",
            "tick_ms_max", "late_ms_max", "smallest_gap_ms"]
    lines = [f"# Two busy cores for {args.seconds:.0f} s, real backend at 30 Hz", "",
             "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(str(r.get(k, "")) for k in keys) + " |" for r in rows]
    (RESULTS / "load.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
