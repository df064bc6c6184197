"""The monitor's cost to the loop: tick jitter (``late_ms``: how late a tick started after its
deadline), tick time and the runtime process's CPU, with 0, 1 and 5 pages open. Each page is
what a browser opens: the two MJPEG images and the event stream, read as fast as they come.

A real ``jetbot-rt run --backend real`` (PCA9685 emulator, videotestsrc at the policy's size,
the bundled policy) at 30 Hz; its telemetry gives every tick's figures; its CPU is read from
/proc (the runtime's process only: the camera's gst-launch child is the same in every case).
The clients run in this process, on the same machine: on a robot the browser is elsewhere.
Writes benchmarks/results/monitor.json and monitor.md.

    python benchmarks/bench_monitor.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np
from versions import stamp

RESULTS = Path(__file__).resolve().parent / "results"
PAGE = ("/stream.mjpg?view=prepared", "/stream.mjpg?view=raw", "/events")
NANO_FACTOR = 4.0
"""A Jetson Nano's A57 core against this machine's, for the JPEG encoding and the Python
around it (single-threaded, scalar code; our own measures of onnxruntime and cv2 on both)."""


def reader(port: int, path: str, stop: threading.Event, received: list[int]) -> None:
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.sendall(f"GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n".encode())
    total = 0
    try:
        while not stop.is_set():
            chunk = sock.recv(1 << 16)
            if not chunk:
                break
            total += len(chunk)
    except OSError:
        pass
    finally:
        sock.close()
        received.append(total)


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def percentile(values: list[float], q: float) -> float:
    return round(float(np.percentile(values, q)), 3) if values else float("nan")


def one_case(pages: int, seconds: float, root: Path) -> dict:
    config = root / f"robot{pages}.toml"
    config.write_text('[camera]\nsource = "gst:videotestsrc is-live=true pattern=ball"\n'
                      "start_timeout = 5\n[loop]\nmax_frame_age = 1.0\nwatchdog_timeout = 1.0\n")
    telemetry = root / f"telemetry{pages}.jsonl"
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(root / "run"))
    process = subprocess.Popen(
        [sys.executable, "-m", "jetbot_rt.cli", "run", "--backend", "real", "--config",
         str(config), "--monitor", "0", "--telemetry", str(telemetry), "--duration",
         str(seconds + 6), "--board-emulator", str(root / "chip.json")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert process.stdout is not None
    port = None
    for line in process.stdout:
        match = re.match(r"monitor: http://127\.0\.0\.1:(\d+)/", line)
        if match:
            port = int(match.group(1))
        if line.startswith("driving at"):
            break
    assert port is not None, process.stderr.read() if process.stderr else ""
    time.sleep(3)  # past the start: the camera and the policy settled
    stop = threading.Event()
    received: list[int] = []
    threads = [threading.Thread(target=reader, args=(port, path, stop, received), daemon=True)
               for _ in range(pages) for path in PAGE]
    for thread in threads:
        thread.start()
    time.sleep(0.5)
    first_tick = json.loads(_get(port, "/state"))["ticks"]
    t0, cpu0 = time.monotonic(), cpu_seconds(process.pid)
    time.sleep(seconds)
    t1, cpu1 = time.monotonic(), cpu_seconds(process.pid)
    state = json.loads(_get(port, "/state"))
    stop.set()
    process.communicate(timeout=60)
    records = [json.loads(line) for line in telemetry.read_text().splitlines()
               if line.endswith("}")]
    in_window = [r for r in records if first_tick < r.get("tick", -1) <= state["ticks"]]
    late = [r["late_ms"] for r in in_window]
    tick = [r["tick_ms"] for r in in_window]
    return {
        "pages": pages, "seconds": round(t1 - t0, 2), "ticks": len(in_window),
        "late_ms": {"p50": percentile(late, 50), "p99": percentile(late, 99),
                    "max": round(max(late), 3)},
        "tick_ms": {"p50": percentile(tick, 50), "p99": percentile(tick, 99),
                    "max": round(max(tick), 3)},
        "overruns": in_window[-1]["overruns"] - in_window[0]["overruns"],
        "cpu_percent": round(100 * (cpu1 - cpu0) / (t1 - t0), 1),
        "stream": state["stream"], "bytes_received": sum(received),
        "exit_code": process.returncode,
    }


def _get(port: int, path: str) -> str:
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.sendall(f"GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n".encode())
    data = b""
    while chunk := sock.recv(1 << 16):
        data += chunk
    sock.close()
    return data.split(b"\r\n\r\n", 1)[1].decode()


def encode_ms() -> float:
    """One 224x224 frame to JPEG, as the server does it once per tick and view."""
    image = np.random.default_rng(0).integers(0, 255, (224, 224, 3), dtype=np.uint8)
    image = cv2.GaussianBlur(image, (9, 9), 3)  # a camera's image compresses like this
    t0 = time.perf_counter()
    for _ in range(200):
        cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return (time.perf_counter() - t0) / 200 * 1e3


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cases = [one_case(pages, args.seconds, Path(tmp)) for pages in (0, 1, 5)]
    encode = round(encode_ms(), 3)
    load = os.getloadavg()
    result = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, load "
                         f"{load[0]:.1f} at the end", "python": platform.python_version(),
              "rate_hz": 30, "jpeg_encode_224_ms": encode, "nano_factor": NANO_FACTOR,
              "cases": cases}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "monitor.json").write_text(json.dumps(stamp(result), indent=1) + "\n")
    base = cases[0]["cpu_percent"]
    lines = [
        "# The monitor's cost to the loop (benchmarks/bench_monitor.py)", "",
        f"`jetbot-rt run --backend real` at 30 Hz (PCA9685 emulator, videotestsrc, the bundled "
        f"policy), {args.seconds:g} s per case, on {result['machine']}; a page is two MJPEG "
        "streams and the event stream, read by clients on the same machine. late = how long "
        "after its deadline a tick started (the jitter); CPU = the runtime process only.", "",
        "| pages | ticks | late p50 | late p99 | late max | tick p99 | overruns | runtime CPU "
        "| monitor's share | frames sent / dropped | est. Nano monitor CPU |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in cases:
        extra = case["cpu_percent"] - base
        lines.append(
            f"| {case['pages']} | {case['ticks']} | {case['late_ms']['p50']} ms "
            f"| {case['late_ms']['p99']} ms | {case['late_ms']['max']} ms "
            f"| {case['tick_ms']['p99']} ms | {case['overruns']} | {case['cpu_percent']} % "
            f"| {extra:+.1f} % | {case['stream']['frames_sent']} / "
            f"{case['stream']['frames_dropped']} | {extra * NANO_FACTOR:+.0f} % of a core |")
    lines += ["", f"One 224x224 JPEG encode: {encode} ms here (about {encode * NANO_FACTOR:.1f} "
              f"ms estimated on a Nano's A57, x{NANO_FACTOR:g}); the server encodes each view at "
              "most once per tick however many pages are open, and nothing without one.", ""]
    (RESULTS / "monitor.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
