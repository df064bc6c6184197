"""How often the stack dump of a stopped service, resumed by systemd's watchdog, crashes: the
old unit's way (WatchdogSignal=SIGABRT: faulthandler dumps every thread from a C signal
handler while SIGCONT has resumed them) against the unit's now (WatchdogSignal=SIGUSR2: the
stacks read in Python, holding the GIL).

The process is tests/test_watchdog_dump.py's churning one (threads that recurse 50-1500 deep
and threads created and ended all the time, so that a frame read a moment late is gone), its
stderr read slowly as a busy journald would. Each trial: SIGSTOP, 0.3 s, then the signals
systemd sends.

    python benchmarks/bench_stack_dump.py [--trials 20]

Writes benchmarks/results/stack_dump.json and stack_dump.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "tests"))

from test_watchdog_dump import churning_process, watchdog_ends  # noqa: E402
from versions import stamp  # noqa: E402


def trial(way: str, seed: int) -> dict:
    process, reader = churning_process("stopped", seed)
    time.sleep(0.2)
    # old: SIGABRT was the watchdog signal, and it ended the process by itself
    play = {"first": signal.SIGABRT, "abort_after": 30.0} if way == "old" else {}
    err = watchdog_ends(process, reader, stopped_for=0.3, **play)
    threads = err.count("most recent call first")
    return {"way": way, "seed": seed, "exit": process.returncode, "threads_dumped": threads}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20)
    args = parser.parse_args()
    started = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    load = os.getloadavg()[0]
    rows = [trial(way, seed) for seed in range(args.trials) for way in ("old", "new")]
    summary = {}
    for way, expected in (("old", -signal.SIGABRT), ("new", 3)):
        mine = [r for r in rows if r["way"] == way]
        summary[way] = {
            "trials": len(mine),
            "crashed_sigsegv": sum(r["exit"] == -signal.SIGSEGV for r in mine),
            "ended_as_designed": sum(r["exit"] == expected for r in mine),
            "no_stack_at_all": sum(r["threads_dumped"] == 0 for r in mine),
        }
    command = f"python benchmarks/bench_stack_dump.py --trials {args.trials}"
    report = {"command": command, "date": started, "load_1min_before": round(load, 2),
              "machine": {"cores": os.cpu_count(), "kernel": platform.release(),
                          "python": platform.python_version()},
              "summary": summary, "trials": rows}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "stack_dump.json").write_text(json.dumps(stamp(report), indent=1) + "\n")
    lines = [
        "# A stopped process's stack dump when systemd's watchdog resumes it", "",
        f"`{command}` on {started}, {os.cpu_count()} cores, Linux {platform.release()}, "
        f"Python {platform.python_version()}, load {load:.2f} before. old: SIGABRT + SIGCONT "
        "(faulthandler from C; designed end: killed by SIGABRT); new: the unit's "
        "WatchdogSignal + SIGCONT, then its FinalKillSignal if needed (designed end: exit 3).",
        "", "| way | trials | crashed (SIGSEGV) | ended as designed | no stack at all |",
        "|---|---|---|---|---|",
        *(f"| {way} | {s['trials']} | {s['crashed_sigsegv']} | {s['ended_as_designed']} | "
          f"{s['no_stack_at_all']} |" for way, s in summary.items()),
    ]
    (RESULTS / "stack_dump.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
