"""The fault tests' measured times (docs/SAFETY.md's "Measured" column), min-max over full runs.

Runs every fault test that records figures (``tests/test_fault_*.py`` that call
``record_figures``, and ``tests/test_hostile_user.py`` and ``tests/test_sim_hiccup.py``, whose
figures SAFETY.md quotes too) ``--runs`` times through pytest with
``JETBOT_RT_FAULT_FIGURES`` set, then takes each case's figures' min and max. A failed test
records nothing (``record_figures`` is each test's last line): its run's other figures stay, and
the run's pytest exit code and failed tests are written down.

    python benchmarks/fault_figures.py [--runs 3] [FILE ...]

Writes benchmarks/results/fault_figures.json (every run's raw records) and .md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from versions import cpu_model, write_results

ROOT = Path(__file__).resolve().parent.parent
EXTRA = ["tests/test_hostile_user.py", "tests/test_sim_hiccup.py"]


def figure_files() -> list[str]:
    faults = sorted((ROOT / "tests").glob("test_fault_*.py"))
    return [str(p.relative_to(ROOT)) for p in faults if "record_figures(" in p.read_text()] + EXTRA


def run_once(files: list[str]) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "figures.jsonl"
        env = {**os.environ, "JETBOT_RT_FAULT_FIGURES": str(path)}
        load, start = os.getloadavg()[0], time.time()
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                               *files], cwd=ROOT, env=env, capture_output=True, text=True)
        lines = path.read_text().splitlines() if path.exists() else []
    out = done.stdout.splitlines()
    run = {"pytest_rc": done.returncode, "summary": out[-1] if out else done.stderr[-300:],
           "failed": [ln for ln in out if ln.startswith(("FAILED", "ERROR"))],
           "wall_s": round(time.time() - start, 1), "load_before": round(load, 2),
           "load_after": round(os.getloadavg()[0], 2),
           "records": [json.loads(line) for line in lines]}
    print(f"run: pytest {done.returncode}, {run['summary']}, {len(lines)} records", flush=True)
    return run


def aggregate(runs: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, Any]]]:
    """{case: {figure: {"min", "max", "runs"}}} over the numbers each run recorded."""
    seen: dict[str, dict[str, dict[int, list[float]]]] = {}
    for i, run in enumerate(runs):
        for record in run["records"]:
            for key, value in record.items():
                if isinstance(value, int | float) and not isinstance(value, bool):
                    cases = seen.setdefault(record["case"], {})
                    cases.setdefault(key, {}).setdefault(i + 1, []).append(value)
    return {case: {key: {"min": min(v for vs in by_run.values() for v in vs),
                         "max": max(v for vs in by_run.values() for v in vs),
                         "runs": sorted(by_run)} for key, by_run in keys.items()}
            for case, keys in sorted(seen.items())}


def markdown(result: dict[str, Any]) -> str:
    lines = ["# Fault tests' measured times, min-max over full runs\n",
             f"`{result['command']}` on {result['date']}, {result['machine']}, "
             f"{result['wall_s']} s, load (1 min) {result['load_start']} -> "
             f"{result['load_end']}. Tests: {', '.join(result['files'])}.\n"]
    for i, run in enumerate(result["runs"], 1):
        failed = f"; failed: {', '.join(run['failed'])}" if run["failed"] else ""
        lines.append(f"- run {i}: pytest exit {run['pytest_rc']}, {run['summary']}, load "
                     f"{run['load_before']} -> {run['load_after']}{failed}")
    lines += ["", "| case | figure | min | max | runs |", "|---|---|---|---|---|"]
    for case, keys in result["figures"].items():
        lines += [f"| {case} | {key} | {f['min']} | {f['max']} | "
                  f"{','.join(map(str, f['runs']))} |" for key, f in keys.items()]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("files", nargs="*", help="test files (default: those that record)")
    args = parser.parse_args()
    files = args.files or figure_files()
    load_start, start = os.getloadavg()[0], time.time()
    runs = [run_once(files) for _ in range(args.runs)]
    result = {
        "command": " ".join(["python benchmarks/fault_figures.py", f"--runs {args.runs}",
                             *args.files]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(start)),
        "machine": f"{cpu_model()}, {os.cpu_count()} cores, {platform.machine()}, "
                   f"Linux {platform.release()}",
        "load_start": round(load_start, 2), "load_end": round(os.getloadavg()[0], 2),
        "wall_s": round(time.time() - start, 1), "files": files,
        "pytest_rc": [run["pytest_rc"] for run in runs],
        "figures": aggregate(runs), "runs": runs,
    }
    write_results(ROOT / "benchmarks" / "results", "fault_figures", result, markdown(result))


if __name__ == "__main__":
    main()
