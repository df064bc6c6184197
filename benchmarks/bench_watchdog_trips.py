"""How often the default 0.1 s in-process watchdog trips with both cores busy, with and without
the unit's scheduling priority (``Nice=`` in jetbot_rt/data/jetbot-rt.service).

The service as it runs on the robot, minus systemd: ``jetbot-rt run --backend real`` with the
bundled policy, a 30 fps ``videotestsrc`` camera and the register-level PCA9685 emulator, the
default ``[loop]`` (30 Hz, watchdog 0.1 s), while two busy-looping processes at nice 0 keep
both cores of this machine busy. Arms, run in alternating chunks so that the rest of the
machine's load (other jobs share it) falls on both alike:

- ``nice0``: the runtime at nice 0, as the unit ran it before;
- ``unit``: the runtime at the unit's ``Nice=`` (set before exec, as systemd does: every
  thread and the camera child inherit it).

A run that trips (exit 3, ``watchdog: no tick for ...``) is counted and started again until
the chunk's time is used. Besides the trips (rare events, few per arm), every tick's telemetry
gives the gaps between consecutive tick starts: a gap over the 0.1 s timeout is a near-certain
trip, and their count per minute estimates the trip rate with many more samples.

    python benchmarks/bench_watchdog_trips.py [--chunk 50] [--rounds 5]

Needs root (a negative nice) and gst-launch-1.0. Writes benchmarks/results/watchdog_trips.json
and watchdog_trips.md with the command, the machine, the date and the load average before
each chunk.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

from versions import stamp

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
UNIT = ROOT / "jetbot_rt" / "data" / "jetbot-rt.service"
JETBOT_RT = shutil.which("jetbot-rt") or str(Path(sys.executable).parent / "jetbot-rt")
BUSY_LOOP = ("import time\nend = time.monotonic() + {seconds}\n"
             "while time.monotonic() < end:\n    pass\n")
CONFIG = '[camera]\nsource = "gst:videotestsrc is-live=true"\nstart_timeout = 30\n'
TIMEOUT_S = 0.1
"""The default watchdog timeout at 30 Hz (three periods, at least 0.1 s)."""


def unit_nice() -> int:
    match = re.search(r"^Nice=(-?\d+)$", UNIT.read_text(), flags=re.MULTILINE)
    if match is None:
        raise SystemExit(f"{UNIT} sets no Nice=")
    return int(match.group(1))


def records_of(telemetry: Path) -> list[dict]:
    records = []
    if telemetry.exists():
        for line in telemetry.read_text().splitlines():
            try:
                records.append(json.loads(line))
            except ValueError:
                continue  # the last line of a killed run
    return records


def one_run(tmp: Path, nice: int, seconds: float) -> dict:
    """One ``jetbot-rt run`` for at most ``seconds`` of driving: its end and its tick gaps."""
    telemetry = tmp / "run.jsonl"
    telemetry.unlink(missing_ok=True)
    chip = tmp / "chip.json"
    chip.unlink(missing_ok=True)
    command = [JETBOT_RT, "run", "--backend", "real", "--config", str(tmp / "robot.toml"),
               "--board-emulator", str(chip), "--duration", f"{seconds:.1f}",
               "--telemetry", str(telemetry)]
    started = time.monotonic()
    done = subprocess.run(command, capture_output=True, text=True, timeout=seconds + 120,
                          preexec_fn=lambda: os.nice(nice) if nice else None, check=False)
    records = records_of(telemetry)
    ticks = [r for r in records if "event" not in r]
    starts = [t["t"] for t in ticks]
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    reasons = [r.get("reason", "") for r in records if r.get("event") == "safe_stop"]
    tripped = done.returncode == 3 and any(r.startswith("watchdog") for r in reasons)
    return {
        "exit_code": done.returncode,
        "tripped": tripped,
        "reason": reasons[0] if reasons else "",
        "wall_s": round(time.monotonic() - started, 2),
        "driving_s": round(starts[-1] - starts[0], 3) if len(starts) > 1 else 0.0,
        "ticks": len(ticks),
        "gaps_over_timeout": sum(g > TIMEOUT_S for g in gaps),
        "gaps_over_half": sum(g > TIMEOUT_S / 2 for g in gaps),
        "max_gap_ms": round(max(gaps) * 1e3, 1) if gaps else None,
        "tick_ms_p99": (round(sorted(t["tick_ms"] for t in ticks)[int(0.99 * (len(ticks) - 1))],
                              2) if ticks else None),
        "overruns": ticks[-1]["overruns"] if ticks else None,
        "error": (done.stderr.strip().splitlines() or [""])[-1][:200]
        if done.returncode not in (0, 3) else "",
    }


def chunk(tmp: Path, arm: str, nice: int, seconds: float) -> dict:
    """``seconds`` of wall time with both cores busy: runs of ``arm`` back to back."""
    load = os.getloadavg()
    hogs = [subprocess.Popen([sys.executable, "-c", BUSY_LOOP.format(seconds=seconds + 5)])
            for _ in range(2)]
    runs = []
    try:
        time.sleep(1.0)  # the hogs are spinning before the runtime starts
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 8.0:
            runs.append(one_run(tmp, nice, left))
            if runs[-1]["exit_code"] not in (0, 3):
                break  # a broken set-up: say so rather than loop
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
    driving = sum(r["driving_s"] for r in runs)
    return {
        "arm": arm, "nice": nice, "load_1min_before": round(load[0], 2),
        "load_5min_before": round(load[1], 2),
        "runs": len(runs), "trips": sum(r["tripped"] for r in runs),
        "driving_s": round(driving, 1),
        "gaps_over_timeout": sum(r["gaps_over_timeout"] for r in runs),
        "gaps_over_half": sum(r["gaps_over_half"] for r in runs),
        "max_gap_ms": max((r["max_gap_ms"] or 0) for r in runs) if runs else None,
        "tick_ms_p99": round(statistics.median([r["tick_ms_p99"] for r in runs
                                                 if r["tick_ms_p99"]]), 2)
        if any(r["tick_ms_p99"] for r in runs) else None,
        "detail": runs,
    }


def per_minute(count: float, seconds: float) -> float | None:
    return round(count * 60 / seconds, 2) if seconds > 0 else None


def summarise(chunks: list[dict], arm: str) -> dict:
    mine = [c for c in chunks if c["arm"] == arm]
    driving = sum(c["driving_s"] for c in mine)
    faults = sum(r["exit_code"] == 3 for c in mine for r in c["detail"])
    return {
        "arm": arm, "nice": mine[0]["nice"], "chunks": len(mine),
        "driving_min": round(driving / 60, 2),
        "trips": sum(c["trips"] for c in mine),
        "trips_per_min": per_minute(sum(c["trips"] for c in mine), driving),
        "faults": faults,
        "faults_per_min": per_minute(faults, driving),
        "gaps_over_0.1s_per_min": per_minute(sum(c["gaps_over_timeout"] for c in mine), driving),
        "gaps_over_0.05s_per_min": per_minute(sum(c["gaps_over_half"] for c in mine), driving),
        "median_chunk_max_gap_ms": round(statistics.median(c["max_gap_ms"] or 0 for c in mine),
                                         1),
        "median_chunk_tick_ms_p99": round(statistics.median(c["tick_ms_p99"] or 0
                                                            for c in mine), 2),
    }


def ratio(a: float | None, b: float | None) -> float | str | None:
    if a is None or b is None:
        return None
    return round(a / b, 2) if b else ("inf" if a else None)


def machine() -> dict:
    model = next((line.split(":", 1)[1].strip()
                  for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor())
    return {"cpu": model, "cores": os.cpu_count(), "kernel": platform.release(),
            "python": platform.python_version()}


def write(chunks: list[dict], args: argparse.Namespace, started: str, wall_s: float) -> None:
    arms = [summarise(chunks, arm) for arm in ("nice0", "unit")]
    base, unit = arms
    ratios = {
        "trips_per_min nice0/unit": ratio(base["trips_per_min"], unit["trips_per_min"]),
        "faults_per_min nice0/unit": ratio(base["faults_per_min"], unit["faults_per_min"]),
        "gaps_over_0.1s_per_min nice0/unit": ratio(base["gaps_over_0.1s_per_min"],
                                                   unit["gaps_over_0.1s_per_min"]),
        "gaps_over_0.05s_per_min nice0/unit": ratio(base["gaps_over_0.05s_per_min"],
                                                    unit["gaps_over_0.05s_per_min"]),
        "median_chunk_max_gap_ms nice0/unit": ratio(base["median_chunk_max_gap_ms"],
                                                    unit["median_chunk_max_gap_ms"]),
    }
    command = " ".join([Path(sys.executable).name, "benchmarks/bench_watchdog_trips.py",
                        "--chunk", f"{args.chunk:g}", "--rounds", str(args.rounds)])
    report = {"command": command, "date": started, "wall_s": round(wall_s), "machine": machine(),
              "arms": arms, "ratios": ratios, "chunks": chunks}
    if args.render:  # the measured run's own facts, not this re-rendering's
        measured = json.loads((RESULTS / "watchdog_trips.json").read_text())
        report.update({k: measured[k] for k in ("command", "date", "wall_s", "machine")})
        command, started = report["command"], report["date"]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "watchdog_trips.json").write_text(json.dumps(stamp(report), indent=1) + "\n")
    keys = list(arms[0])
    lines = [
        "# Watchdog trips with both cores busy: nice 0 against the unit's Nice=", "",
        f"`{command}` on {started}, {report['machine']['cores']} cores "
        f"({report['machine']['cpu']}), Linux {report['machine']['kernel']}, "
        f"{report['wall_s']} s of wall time. Two busy loops at nice 0; `jetbot-rt run "
        "--backend real`, bundled policy, 30 fps videotestsrc, emulated board, default "
        "[loop] (30 Hz, watchdog 0.1 s). Chunks alternate between the arms; the machine is "
        "shared with other jobs (load average before each chunk below).", "",
        "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys),
        *("| " + " | ".join(str(a[k]) for k in keys) + " |" for a in arms), "",
        "Ratios (nice0 / unit, same run): "
        + ", ".join(f"{k} = {v}" for k, v in ratios.items()), "",
        "trips: watchdog stops (exit 3, `watchdog: no tick ...`); faults: every exit 3 (the "
        "others were `stale frame`: the camera starved). Each chunk's runs, in order:", "",
        "| chunk | arm | load 1 min | runs: exit, driving s, reason | gaps > 0.05 s "
        "| max gap ms | tick ms p99 |", "|---|---|---|---|---|---|---|",
        *(f"| {i} | {c['arm']} | {c['load_1min_before']} | "
          + "; ".join(f"{r['exit_code']}, {r['driving_s']:.1f} s, {r['reason'].split(' (')[0]}"
                      for r in c["detail"])
          + f" | {c['gaps_over_half']} | {c['max_gap_ms']} | {c['tick_ms_p99']} |"
          for i, c in enumerate(chunks)),
    ]
    (RESULTS / "watchdog_trips.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chunk", type=float, default=50.0, help="seconds per chunk")
    parser.add_argument("--rounds", type=int, default=5, help="chunks per arm")
    parser.add_argument("--render", action="store_true",
                        help="only write the tables again from results/watchdog_trips.json")
    args = parser.parse_args()
    if args.render:
        measured = json.loads((RESULTS / "watchdog_trips.json").read_text())
        write(measured["chunks"], args, measured["date"], measured["wall_s"])
        return
    if os.geteuid() != 0:
        raise SystemExit("needs root: the unit's Nice= is negative")
    if shutil.which("gst-launch-1.0") is None:
        raise SystemExit("needs gst-launch-1.0 (gstreamer1.0-tools)")
    arms = {"nice0": 0, "unit": unit_nice()}
    started = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    t0 = time.monotonic()
    chunks: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="jetbot-rt-trips-") as directory:
        tmp = Path(directory)
        (tmp / "robot.toml").write_text(CONFIG)
        for round_index in range(args.rounds):
            # alternate which arm goes first, so neither always follows the other
            order = list(arms) if round_index % 2 == 0 else list(reversed(arms))
            for arm in order:
                chunks.append(chunk(tmp, arm, arms[arm], args.chunk))
                last = chunks[-1]
                print(f"round {round_index} {arm}: load {last['load_1min_before']}, "
                      f"{last['runs']} runs, {last['trips']} trips, "
                      f"{last['gaps_over_timeout']} gaps > 0.1 s in {last['driving_s']} s",
                      flush=True)
    write(chunks, args, started, time.monotonic() - t0)


if __name__ == "__main__":
    main()
