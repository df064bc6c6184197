"""Soak: the sim loop at 30 Hz for a long time; rate, tick times, overruns, memory growth.

Runs ``jetbot-rt run --backend sim`` as a child process (the product as a user runs it),
samples its resident memory from /proc every few seconds, and reads its telemetry.

    python benchmarks/soak.py [--minutes 10] [--policy P] [--out benchmarks/results/soak.json]
        [--beside "a command kept running beside it"]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from versions import stamp

RESULTS = Path(__file__).resolve().parent / "results"


def rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--rate", type=float, default=30.0)
    parser.add_argument("--policy", help="ONNX policy (default: the bundled one)")
    parser.add_argument("--sample-every", type=float, default=5.0, help="seconds between RSS reads")
    parser.add_argument("--out", default=str(RESULTS / "soak.json"))
    parser.add_argument("--beside", metavar="COMMAND",
                        help="a shell command kept running beside the soak (started again "
                             "when it ends, ended with it): the load of a loaded run")
    args = parser.parse_args()

    exe = shutil.which("jetbot-rt") or str(Path(sys.executable).parent / "jetbot-rt")
    with tempfile.TemporaryDirectory() as tmp:
        telemetry = Path(tmp) / "soak.jsonl"
        cmd = [exe, "run", "--backend", "sim", "--rate", str(args.rate),
               "--duration", str(args.minutes * 60), "--telemetry", str(telemetry)]
        if args.policy:
            cmd += ["--policy", args.policy]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        beside, starts = None, 0
        samples: list[tuple[float, float]] = []
        loads: list[float] = []
        t0 = time.monotonic()
        try:
            while proc.poll() is None:
                if args.beside and (beside is None or beside.poll() is not None):
                    beside = subprocess.Popen(["sh", "-c", args.beside], start_new_session=True,
                                              stdout=subprocess.DEVNULL,
                                              stderr=subprocess.DEVNULL)
                    starts += 1
                value = rss_mib(proc.pid)
                if value is not None:
                    samples.append((time.monotonic() - t0, value))
                loads.append(os.getloadavg()[0])
                time.sleep(args.sample_every)
        finally:
            if beside is not None and beside.poll() is None:
                os.killpg(beside.pid, signal.SIGKILL)
                beside.wait()
        stdout, stderr = proc.communicate()
        records = [json.loads(line) for line in telemetry.read_text().splitlines()]

    ticks = [r for r in records if "event" not in r]
    end = records[-1]
    tick_ms = np.array([r["tick_ms"] for r in ticks])
    late_ms = np.array([r["late_ms"] for r in ticks])
    # memory after warm-up (first minute) versus the end: growth must be flat
    warmup_s = min(60.0, args.minutes * 30)
    steady = [(t, m) for t, m in samples if t >= warmup_s] or samples
    warm = [m for _, m in steady]
    slope = (np.polyfit([t for t, _ in steady], warm, 1)[0] * 3600
             if len(steady) > 2 else float("nan"))
    result = {
        "minutes": args.minutes,
        "rate_hz": args.rate,
        "exit_code": proc.returncode,
        "end_reason": end.get("reason"),
        "ticks": len(ticks),
        "achieved_hz": end.get("achieved_hz"),
        "overruns": end.get("overruns"),
        "tick_ms": {"p50": round(float(np.percentile(tick_ms, 50)), 3),
                    "p99": round(float(np.percentile(tick_ms, 99)), 3),
                    "max": round(float(tick_ms.max()), 3)},
        "start_jitter_ms": {"p50": round(float(np.percentile(late_ms, 50)), 3),
                            "p99": round(float(np.percentile(late_ms, 99)), 3),
                            "max": round(float(late_ms.max()), 3)},
        "rss_mib": {"start": round(samples[0][1], 1), "after_warmup": round(warm[0], 1),
                    "end": round(samples[-1][1], 1), "max": round(max(m for _, m in samples), 1),
                    "growth_after_warmup": round(samples[-1][1] - warm[0], 1),
                    "slope_mib_per_hour": round(float(slope), 2)},
        "rss_samples": len(samples),
        "beside": args.beside, "beside_starts": starts,
        "loadavg_1min": {"median": round(float(np.median(loads)), 2),
                         "max": round(max(loads), 2)},
        "stderr": stderr.strip()[-500:],
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(stamp(result), indent=2) + "\n")
    print(json.dumps(result, indent=2))
    print(stdout)


if __name__ == "__main__":
    main()
