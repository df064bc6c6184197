"""What ``--record`` costs: loop jitter and tick time with and without it, in the same run, and
the disk and CPU time per minute of recording.

``jetbot-rt run`` as a subprocess at 30 Hz on the real backend: the emulated PCA9685 and a
live GStreamer camera (a photo at 30 fps, scaled to 224x224), the bundled policy. Runs
alternate without / with ``--record`` (``--pairs`` of each), so both see the same machine.
Writes benchmarks/results/record.json and record.md: tick-start jitter p99 and tick time with
vs without, ticks lost (deadlines skipped: overruns), frames dropped and records lost, disk
and CPU per minute of recording.

    python benchmarks/bench_record.py     # 2 pairs of 30 s runs: ~2.5 min on an idle machine
    python benchmarks/bench_record.py [--seconds 30] [--pairs 2] [--backend real|sim]
                                      [--camera photo|ball|snow]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from runner import RuntimeProcess
from versions import stamp

from jetbot_rt.runtime.policy import bundled_policy_path

RESULTS = Path(__file__).resolve().parent / "results"
SOURCES = {
    # a photo (matplotlib's sample Grace Hopper portrait) as a live 30 fps camera: FFV1 codes
    # each frame on its own, so its size per frame is that of a real scene, without noise
    "photo": "filesrc location={photo} ! jpegdec ! imagefreeze is-live=true ! videoconvert ! "
             "video/x-raw,framerate=30/1",
    "ball": "videotestsrc is-live=true pattern=ball ! video/x-raw,framerate=30/1",
    "snow": "videotestsrc is-live=true pattern=snow ! video/x-raw,framerate=30/1",  # worst case
}


def camera_config(name: str) -> str:
    photo = ""
    if name == "photo":
        import matplotlib.cbook

        photo = matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
    source = SOURCES[name].format(photo=photo)
    return f'[camera]\nsource = "gst:{source}"\nstart_timeout = 10\n'


# The watchdog's 3 periods would end a run on a machine shared with other jobs; what is
# measured here is the schedule, so a late tick is counted (overruns), not a fault.
PATIENT = "[loop]\nwatchdog_timeout = 1.0\n"


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def one_run(root: Path, backend: str, seconds: float, record: bool, camera: str,
            extra_config: str = "") -> dict:
    """One run; ``extra_config`` (TOML) is added to its config (bench_record_codecs.py: the
    ``[record] codec``)."""
    root.mkdir(parents=True)
    runtime = RuntimeProcess(root, backend, bundled_policy_path(), duration=seconds,
                             config=PATIENT + (camera_config(camera) if backend == "real"
                                               else "") + extra_config)
    rec = root / "rec"
    if record:
        runtime.args += ["--record", str(rec)]
    load = os.getloadavg()[0]
    cpu = children_cpu()
    result = runtime.start().finish(timeout=seconds + 120)
    cpu = children_cpu() - cpu
    if result.returncode != 0:
        raise SystemExit(f"run failed ({result.returncode}): {result.stdout}{result.stderr}")
    ticks = result.ticks
    late = np.array([r["late_ms"] for r in ticks])
    tick = np.array([r["tick_ms"] for r in ticks])
    end = result.events("end")[0]
    out = {
        "record": record,
        "ticks": len(ticks),
        "expected_ticks": int(seconds * 30),
        "overruns": end.get("overruns"),
        "late_ms_p50": round(float(np.percentile(late, 50)), 3),
        "late_ms_p99": round(float(np.percentile(late, 99)), 3),
        "tick_ms_p50": round(float(np.percentile(tick, 50)), 3),
        "tick_ms_p99": round(float(np.percentile(tick, 99)), 3),
        "cpu_s": round(cpu, 2),
        "load_1min_before": round(load, 2),
    }
    if record:
        counts = end["recording"]
        size = sum(p.stat().st_size for p in rec.iterdir())
        out.update(frames_written=counts["frames_written"],
                   frames_dropped=counts["frames_dropped"],
                   records_lost=counts["records_lost"], disk_bytes=size,
                   codec=json.loads((rec / "meta.json").read_text()).get("codec"))
    return out


def pooled(runs: list[dict], key: str) -> float:
    return round(float(np.mean([r[key] for r in runs])), 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--pairs", type=int, default=2)
    parser.add_argument("--backend", default="real", choices=["real", "sim"])
    parser.add_argument("--camera", default="photo", choices=sorted(SOURCES),
                        help="what the real backend's camera shows (default photo)")
    args = parser.parse_args()
    runs: list[dict] = []
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for pair in range(args.pairs):
            for record in (False, True):
                run = one_run(Path(tmp) / f"{pair}-{record}", args.backend, args.seconds,
                              record, args.camera)
                runs.append(run)
                print(json.dumps(run), flush=True)
    plain = [r for r in runs if not r["record"]]
    rec = [r for r in runs if r["record"]]
    minutes = args.seconds / 60.0
    summary = {
        "backend": args.backend,
        "camera": args.camera if args.backend == "real" else "sim",
        "seconds_per_run": args.seconds,
        "pairs": args.pairs,
        **{key: {"without": pooled(plain, key), "with": pooled(rec, key)}
           for key in ("late_ms_p99", "tick_ms_p50", "tick_ms_p99")},
        "overruns": {"without": sum(r["overruns"] for r in plain),
                     "with": sum(r["overruns"] for r in rec)},
        "ticks": {"without": sum(r["ticks"] for r in plain), "with": sum(r["ticks"] for r in rec)},
        "expected_ticks": {"without": sum(r["expected_ticks"] for r in plain),
                           "with": sum(r["expected_ticks"] for r in rec)},
        "frames_dropped": sum(r["frames_dropped"] for r in rec),
        "records_lost": sum(r["records_lost"] for r in rec),
        "disk_mb_per_min": round(pooled(rec, "disk_bytes") / 1e6 / minutes, 2),
        "cpu_s_per_min": {"without": round(pooled(plain, "cpu_s") / minutes, 2),
                          "with": round(pooled(rec, "cpu_s") / minutes, 2)},
        "load_1min": [r["load_1min_before"] for r in runs],
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
        "wall_s": round(time.perf_counter() - began, 1),
        "runs": runs,
    }
    jitter = summary["late_ms_p99"]
    summary["late_p99_ratio"] = round(jitter["with"] / jitter["without"], 3) \
        if jitter["without"] else None
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "record.json").write_text(json.dumps(stamp(summary), indent=1) + "\n")
    cpu = summary["cpu_s_per_min"]
    extra_cpu = cpu["with"] - cpu["without"]
    gb_per_hour = summary["disk_mb_per_min"] * 60 / 1e3
    (RESULTS / "record.md").write_text(
        f"# Recording cost ({time.strftime('%Y-%m-%d')}, `bench_record.py --backend "
        f"{args.backend} --camera {args.camera} --seconds {args.seconds:g} --pairs "
        f"{args.pairs}`)\n\n"
        f"{os.cpu_count()} cores, 1-min load before each run: {summary['load_1min']}; the "
        f"benchmark took {summary['wall_s']} s\n\n"
        "| | without --record | with --record |\n| --- | --- | --- |\n"
        f"| tick start jitter p99 (late_ms) | {jitter['without']} ms | {jitter['with']} ms "
        f"(x{summary['late_p99_ratio']}) |\n"
        f"| tick time p50 / p99 | {summary['tick_ms_p50']['without']} / "
        f"{summary['tick_ms_p99']['without']} ms | {summary['tick_ms_p50']['with']} / "
        f"{summary['tick_ms_p99']['with']} ms |\n"
        f"| ticks run / expected at 30 Hz | {summary['ticks']['without']} / "
        f"{summary['expected_ticks']['without']} | {summary['ticks']['with']} / "
        f"{summary['expected_ticks']['with']} |\n"
        f"| ticks lost (deadlines skipped: overruns) | {summary['overruns']['without']} | "
        f"{summary['overruns']['with']} |\n"
        f"| CPU time per minute (runtime, camera, writer) | {cpu['without']} s | "
        f"{cpu['with']} s |\n\n"
        f"Recording: {summary['disk_mb_per_min']} MB per minute of driving "
        f"({gb_per_hour:.1f} GB per hour), {summary['frames_dropped']} frames dropped, "
        f"{summary['records_lost']} tick records lost; the extra CPU is "
        f"{extra_cpu:.1f} s per minute ({extra_cpu / 60:.0%} of one core).\n")
    print(json.dumps({k: v for k, v in summary.items() if k != "runs"}))


if __name__ == "__main__":
    main()
