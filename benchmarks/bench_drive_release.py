"""How long after a person lets go of a key the wheels are at zero (``jetbot-rt drive --input
keyboard``, docs/DRIVE.md): a sim drive on a real pty, a key held (sent every 33 ms, as a
terminal's auto-repeat) for 0.5 s, then released; the time from the last key byte to the
first tick whose command is zero, as the telemetry file shows it (so an upper bound: it
includes the telemetry writer's delay). Repeated ``--releases`` times in one drive.

    python benchmarks/bench_drive_release.py --releases 10 \
        --out benchmarks/results/drive_release.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import pty
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from versions import stamp

JETBOT_RT = shutil.which("jetbot-rt") or str(Path(sys.executable).parent / "jetbot-rt")


def ticks(path: Path) -> list[dict]:
    found = []
    if not path.exists():
        return found
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            break
        if "tick" in record:
            found.append(record)
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--releases", type=int, default=10)
    parser.add_argument("--deadman", type=float, default=0.25)
    parser.add_argument("--out")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp())
    telemetry = work / "telemetry.jsonl"
    master, slave = pty.openpty()
    proc = subprocess.Popen([JETBOT_RT, "drive", "--backend", "sim", "--input", "keyboard",
                             "--deadman", str(args.deadman), "--telemetry", str(telemetry)],
                            stdin=slave, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    delays = []
    try:
        while not ticks(telemetry):
            time.sleep(0.05)
        for _ in range(args.releases):
            end = time.monotonic() + 0.5
            while time.monotonic() < end:
                os.write(master, b"w")
                last = time.monotonic()
                time.sleep(0.033)
            seen = len(ticks(telemetry))
            while True:
                records = ticks(telemetry)
                fresh = [r for r in records[seen - 1:] if r.get("human") is None]
                if fresh:
                    delays.append(time.monotonic() - last)
                    break
                time.sleep(0.002)
            time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
        os.close(slave)
    result = {
        "command": " ".join(sys.argv), "deadman_s": args.deadman, "releases": len(delays),
        "release_to_zero_ms": {"min": round(min(delays) * 1e3, 1),
                               "median": round(sorted(delays)[len(delays) // 2] * 1e3, 1),
                               "max": round(max(delays) * 1e3, 1)},
        "exit_code": proc.returncode, "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "load_average": os.getloadavg(), "date": time.strftime("%Y-%m-%d %H:%M UTC",
                                                               time.gmtime()),
    }
    print(json.dumps(result, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(stamp(result), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
