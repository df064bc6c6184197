"""The test suite's wall time: the README's test command (``pytest -q -n 2``), timed, its
summary line parsed, with the machine, its load before and after, and the versions.

    python benchmarks/time_suite.py [--out benchmarks/results/test_suite.json] [-- PYTEST ARGS]

The budget it is read against (6 minutes on a 2-core machine) is a working rule, never a
test's assertion.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from versions import stamp

SUMMARY = re.compile(r"^=*\s*(?P<line>(\d+ \w+(, )?)+ in [\d.]+s.*?)\s*=*$")


def summary_counts(line: str) -> dict[str, int]:
    """``{"passed": 1592, "skipped": 2, ...}`` from pytest's last line."""
    return {word: int(count) for count, word in re.findall(r"(\d+) (\w+)", line.split(" in ")[0])}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/test_suite.json")
    parser.add_argument("pytest_args", nargs="*", default=["-q", "-n", "2"])
    args = parser.parse_args()
    command = [sys.executable, "-m", "pytest", *args.pytest_args, "-p", "no:cacheprovider"]
    load_before = os.getloadavg()
    began = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - began
    lines = [m.group("line") for m in map(SUMMARY.match, done.stdout.splitlines()) if m]
    result = {
        "command": "python benchmarks/time_suite.py " + " ".join(args.pytest_args),
        "pytest": " ".join(["python", "-m", "pytest", *args.pytest_args]),
        "exit_code": done.returncode,
        "summary": lines[-1] if lines else None,
        "counts": summary_counts(lines[-1]) if lines else {},
        "wall_s": round(wall, 1),
        "machine": f"{platform.node()}, {os.cpu_count()} cores, {platform.platform()}",
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()],
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    }
    Path(args.out).write_text(json.dumps(stamp(result), indent=1) + "\n")
    print(f"{result['summary']} (wall {wall:.0f} s); wrote {args.out}")
    return done.returncode


if __name__ == "__main__":
    sys.exit(main())
