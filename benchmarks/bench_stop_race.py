"""How often a runtime reached by ``jetbot-rt stop`` still ends as a fault (exit 3).

``stop`` puts the chip to sleep before it asks the runtimes to end, so a tick can write
between the two and find the chip asleep (``BoardAsleep``); the loop gives the request
``BoardAsleep.STOP_REQUEST_GRACE_S`` to arrive. Each trial starts ``jetbot-rt run --backend
real`` (emulated board, ``videotestsrc``, default ``[loop]``), waits for 15 ticks, runs
``jetbot-rt stop`` and counts the pair (stop's exit, the runtime's exit).

    python benchmarks/bench_stop_race.py --trials 40

Writes benchmarks/results/stop_race.json and .md.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from test_real_backend_e2e import Robot  # noqa: E402
from versions import stamp  # noqa: E402


def trial() -> tuple[int, int]:
    with tempfile.TemporaryDirectory() as directory:
        robot = Robot(Path(directory))
        try:
            robot.start()
            robot.wait_for_ticks(15)
            stop = subprocess.run([sys.executable, "-m", "jetbot_rt.cli", "stop", *robot.board],
                                  capture_output=True, text=True, timeout=30, env=robot.env)
            code, _out, _err = robot.finish()
            return stop.returncode, code
        finally:
            robot.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=40)
    args = parser.parse_args()
    load_before = os.getloadavg()
    start = time.time()
    pairs = collections.Counter(trial() for _ in range(args.trials))
    result = {
        "command": f"python benchmarks/bench_stop_race.py --trials {args.trials}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(start)),
        "machine": f"{os.cpu_count()} cores, {platform.machine()}, Linux {platform.release()}",
        "load_before": load_before, "load_after": os.getloadavg(),
        "wall_s": round(time.time() - start, 1),
        "outcomes": {f"stop {s}, runtime {r}": n for (s, r), n in sorted(pairs.items())},
    }
    out = ROOT / "benchmarks" / "results"
    (out / "stop_race.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    lines = ["# A reached runtime's exit after `jetbot-rt stop`\n",
             f"`{result['command']}` on {result['date']}, {result['machine']}, "
             f"{result['wall_s']} s, load {load_before[0]:.2f} -> {result['load_after'][0]:.2f}.\n",
             "| outcome | trials |", "|---|---|"]
    lines += [f"| {name} | {n} |" for name, n in result["outcomes"].items()]
    (out / "stop_race.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
