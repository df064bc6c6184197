"""Control-loop benchmarks: tick start jitter, loop overhead, watchdog stop latency.

Null camera and drive (no I/O) and a tiny real ONNX policy, so what is measured is the loop.
Writes benchmarks/results/loop.json and loop.md.

    python benchmarks/bench_loop.py [--seconds 20] [--trials 60]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import policy_models
from versions import stamp

from jetbot_rt.recording.telemetry import Telemetry
from jetbot_rt.runtime.actions import ActionPipeline
from jetbot_rt.runtime.loop import ControlLoop, Schedule, StopChain
from jetbot_rt.runtime.policy import OnnxPolicy
from jetbot_rt.runtime.safety import GuardedDrive, SafeStopLatch, Watchdog
from jetbot_rt.testing.null_robot import NullDrive, PartsRobot

RESULTS = Path(__file__).resolve().parent / "results"


def stats(values: list[float] | np.ndarray) -> dict[str, float]:
    array = np.asarray(values, dtype=float)
    return {
        "n": int(array.size),
        "p50": round(float(np.percentile(array, 50)), 4),
        "p99": round(float(np.percentile(array, 99)), 4),
        "max": round(float(array.max()), 4),
    }


def build_loop(policy, period: float, telemetry: Telemetry, watchdog_timeout: float | None,
               drive: NullDrive | None = None):
    latch = SafeStopLatch()
    drive = drive or NullDrive()
    guarded = GuardedDrive(drive, latch)
    watchdog = Watchdog(latch, watchdog_timeout) if watchdog_timeout else None
    loop = ControlLoop(
        robot=PartsRobot(drive=drive), policy=policy, actions=ActionPipeline(),
        safety=StopChain(latch, guarded, watchdog), schedule=Schedule(period, max_frame_age=1.0),
        observers=[telemetry.observe] if telemetry.enabled else [],
    )
    return loop, latch, watchdog


def telemetry_records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if "event" not in line]


def jitter(policy, rate: float, seconds: float, workdir: Path) -> dict:
    telemetry = Telemetry(workdir / f"jitter_{rate:g}.jsonl")
    loop, _, watchdog = build_loop(policy, 1.0 / rate, telemetry, 3.0 / rate)
    watchdog.start()
    loop.run(duration=seconds)
    watchdog.close()
    telemetry.close()
    late = [r["late_ms"] for r in telemetry_records(workdir / f"jitter_{rate:g}.jsonl")]
    return {
        "rate_hz": rate,
        "ticks": loop.stats.ticks,
        "achieved_hz": round(loop.stats.achieved_hz, 3),
        "overruns": loop.stats.overruns,
        "start_jitter_ms": stats(late),
        "infer_ms_p50": round(loop.stats.infer_ms.percentile(50), 4),
    }


def sleep_floor(rate: float, seconds: float) -> dict:
    """Baseline: a bare ``time.sleep`` to absolute deadlines, no loop around it. What the OS
    scheduler alone costs; the loop's jitter is compared with this, measured in the same run."""
    period = 1.0 / rate
    late = []
    deadline = time.monotonic()
    for _ in range(int(seconds * rate)):
        deadline += period
        time.sleep(max(0.0, deadline - time.monotonic()))
        late.append((time.monotonic() - deadline) * 1e3)
    return {"rate_hz": rate, "start_jitter_ms": stats(late)}


def overhead(policy, ticks: int, workdir: Path) -> dict:
    """Free-running loop (period ~0): per-tick wall time minus the inference it contained."""
    telemetry = Telemetry(workdir / "overhead.jsonl")
    loop, latch, _ = build_loop(policy, 1e-6, telemetry, None)
    original = loop._tick
    marks: list[tuple[float, float]] = []

    def counting_tick(deadline: float, now: float) -> None:
        original(deadline, now)
        marks.append((now, loop.stats.infer_ms.last))
        if len(marks) >= ticks:
            latch.trip("enough ticks", fault=False)

    loop._tick = counting_tick
    loop.run()
    telemetry.close()
    starts = np.array([m[0] for m in marks])
    infer = np.array([m[1] for m in marks])
    per_tick_ms = np.diff(starts) * 1e3 - infer[:-1]
    return {"ticks": len(marks), "overhead_ms": stats(per_tick_ms),
            "note": "tick wall time minus inference; includes camera read (null), actions, "
                    "guarded write, watchdog kick, telemetry JSON line to a file, deadline "
                    "bookkeeping"}


class StampingDrive(NullDrive):
    def __init__(self) -> None:
        super().__init__()
        self.t_stop: float | None = None

    def stop(self) -> None:
        super().stop()
        if self.t_stop is None:
            self.t_stop = time.monotonic()


class HangAfter:
    def __init__(self, policy, ticks: int, hang: float) -> None:
        self.policy, self.ticks, self.hang, self.calls = policy, ticks, hang, 0

    def infer(self, image):
        self.calls += 1
        if self.calls > self.ticks:
            time.sleep(self.hang)
        return self.policy.infer(image)


def watchdog_latency(policy, trials: int, rate: float, workdir: Path) -> dict:
    timeout = 3.0 / rate
    excess_ms = []
    for _ in range(trials):
        drive = StampingDrive()
        telemetry = Telemetry(None)
        loop, latch, watchdog = build_loop(
            HangAfter(policy, 5, 3 * timeout), 1.0 / rate, telemetry, timeout, drive
        )
        kicks: list[float] = []
        original_kick = watchdog.kick

        def stamped_kick(original=original_kick, kicks=kicks) -> None:
            kicks.append(time.monotonic())
            original()

        watchdog.kick = stamped_kick
        watchdog.start()
        loop.run(duration=5.0)
        watchdog.close()
        assert latch.reason and latch.reason.startswith("watchdog"), latch.reason
        excess_ms.append((drive.t_stop - kicks[-1] - timeout) * 1e3)
    return {"trials": trials, "timeout_ms": round(timeout * 1e3, 3),
            "stop_after_timeout_ms": stats(excess_ms),
            "all_within_10ms": bool(max(excess_ms) <= 10.0)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="per jitter run")
    parser.add_argument("--trials", type=int, default=60, help="watchdog trials")
    parser.add_argument("--overhead-ticks", type=int, default=3000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        policy = OnnxPolicy.load(policy_models.constant(workdir / "tiny.onnx", (1.0, 1.0)))
        results = {
            "machine": f"{platform.node()} {platform.processor() or platform.machine()}, "
                       f"Python {platform.python_version()}",
            "policy": "constant ONNX (ReduceMean over the 224x224x3 frame)",
            "jitter": [jitter(policy, rate, args.seconds, workdir) for rate in (30.0, 100.0)],
            "sleep_baseline": [sleep_floor(rate, args.seconds) for rate in (30.0, 100.0)],
            "overhead": overhead(policy, args.overhead_ticks, workdir),
            "watchdog": watchdog_latency(policy, args.trials, 30.0, workdir),
        }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "loop.json").write_text(json.dumps(stamp(results), indent=2) + "\n")
    lines = ["| measure | p50 | p99 | max | target |", "|---|---|---|---|---|"]
    for run, base in zip(results["jitter"], results["sleep_baseline"], strict=True):
        j, b = run["start_jitter_ms"], base["start_jitter_ms"]
        lines.append(f"| tick start jitter @ {run['rate_hz']:g} Hz ({run['ticks']} ticks, "
                     f"{run['overruns']} overruns) | {j['p50']} ms | {j['p99']} ms | "
                     f"{j['max']} ms | p99 <= 1 ms |")
        lines.append(f"| baseline: bare time.sleep to deadlines @ {base['rate_hz']:g} Hz "
                     f"(loop/baseline p99: x{j['p99'] / b['p99']:.2f}) | {b['p50']} ms | "
                     f"{b['p99']} ms | {b['max']} ms | |")
    o = results["overhead"]["overhead_ms"]
    lines.append(f"| loop overhead per tick (excl. inference) | {o['p50']} ms | {o['p99']} ms | "
                 f"{o['max']} ms | <= 0.3 ms |")
    w = results["watchdog"]["stop_after_timeout_ms"]
    lines.append(f"| watchdog stop after timeout ({results['watchdog']['trials']} trials, "
                 f"timeout {results['watchdog']['timeout_ms']} ms) | {w['p50']} ms | {w['p99']} ms"
                 f" | {w['max']} ms | <= 10 ms every trial |")
    (RESULTS / "loop.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
