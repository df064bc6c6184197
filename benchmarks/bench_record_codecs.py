"""The recording's choices in docs/RECORDING.md, re-measured in one run on this machine: the
frames' codec (CPU and size per frame, MB per minute at the recording's rate, whether a decode
gives the very pixels back), the bundled policy's ``mu`` on frames that went through each codec
against the ``mu`` it recorded, the report video's codec (mp4v against VP9), and the control
loop's jitter without recording, recording HuffYUV and recording FFV1.

    python benchmarks/bench_record_codecs.py [--rounds 5] [--frames 300] [--loop-rounds 3]
        [--loop-seconds 20] [--sim-seconds 10] [--out benchmarks/results]

1. A ``jetbot-rt run --backend sim --record`` of ``--sim-seconds`` at 30 Hz (the bundled
   policy, HuffYUV: the default) gives the sim frames and the ``mu`` the policy computed on
   them.
2. Codecs: each frame set (the sim frames; a photo, matplotlib's Grace Hopper portrait, fitted
   to the bundled policy's 56x56 input as the real camera's frames are; the photo at 224x224,
   the input of a larger policy) is encoded ``--frames`` frames at a time through OpenCV as the
   writer process does (HuffYUV and FFV1 in Matroska; MJPG too), and per frame as PNG (zlib
   level 1) and JPEG (quality 95 and 75); uncompressed RGB is the size baseline. CPU time is
   the process's (every thread), from opening the writer to releasing it, per frame.
3. ``mu``: the policy (``jetbot-rt replay``'s, with the recorded ``[policy]``) on each codec's
   decoded sim frames against the recorded ``mu``: the largest absolute difference over ticks
   and both wheels, as replay's ``mu_max_abs_diff`` (baseline: replay of the recording itself).
4. The report's video: ``report``'s own frames (``compose``, 448x568 for 56x56 frames) written
   as mp4v (what pip's OpenCV writes for ``run.mp4``) and as VP9 in WebM.
5. The loop: ``bench_record.one_run`` (``jetbot-rt run --backend real`` at 30 Hz, emulated board,
   the photo as a live GStreamer camera) for ``--loop-seconds`` without ``--record``, with
   ``--record`` (HuffYUV) and with ``[record] codec = "ffv1"``.

Variants are interleaved in rounds, each round in a rotated order, so a drift in the machine's
load falls on all alike; figures are medians over rounds. The writer thread that the writer
process replaced (``queue.Queue`` or lock-free hand-over) is not in the code any more (82dd2c2)
and is not measured. Writes record_codecs.json and record_codecs.md to --out.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from bench_record import PATIENT, one_run
from runner import RuntimeProcess
from versions import cpu_model, run_record, write_results

from jetbot_rt.commands.replay import policy_config, replay
from jetbot_rt.commands.report import compose, stderr_silenced
from jetbot_rt.recording.reader import Recording
from jetbot_rt.runtime.policy import OnnxPolicy, bundled_policy_path

RESULTS = Path(__file__).resolve().parent / "results"
RATE_HZ = 30.0

VIDEO_CODECS: dict[str, tuple[str, str]] = {
    # name: (fourcc, container) as cv2.VideoWriter takes them
    "huffyuv": ("HFYU", ".mkv"),
    "ffv1": ("FFV1", ".mkv"),
    "mjpg": ("MJPG", ".mkv"),
}
IMAGE_CODECS: dict[str, tuple[str, list[int]]] = {
    "png1": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 1]),
    "jpeg95": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95]),
    "jpeg75": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 75]),
}
CODEC_NAMES = [*VIDEO_CODECS, *IMAGE_CODECS]
LABELS = {
    "raw": "uncompressed RGB (baseline)",
    "huffyuv": "HuffYUV (default)",
    "ffv1": 'FFV1 (`codec = "ffv1"`)',
    "mjpg": "MJPG (OpenCV's default quality; lossy)",
    "png1": "PNG, zlib level 1 (a file per frame)",
    "jpeg95": "JPEG quality 95 (lossy)",
    "jpeg75": "JPEG quality 75 (lossy)",
}
REPORT_CODECS: dict[str, tuple[str, str]] = {"mp4v": ("mp4v", ".mp4"), "vp9": ("VP90", ".webm")}
LOOP_VARIANTS: dict[str, tuple[bool, str]] = {
    # name: (--record, extra config)
    "without": (False, ""),
    "huffyuv": (True, ""),
    "ffv1": (True, '[record]\ncodec = "ffv1"\n'),
}


def median(values: list[float]) -> float:
    return float(np.median(values))


def rotated(names: list[str], shift: int) -> list[str]:
    shift %= len(names)
    return names[shift:] + names[:shift]


def photo() -> np.ndarray:
    """matplotlib's sample photo, RGB: what bench_record's live camera shows."""
    import matplotlib.cbook

    path = matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
    bgr = cv2.imread(str(path))
    if bgr is None:
        raise SystemExit(f"cannot read {path}")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def fitted(image: np.ndarray, size: int) -> np.ndarray:
    """``image`` at size x size the way ``OnnxPolicy.fit`` brings a frame to its input."""
    return cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)


# ---- 1. the sim recording ------------------------------------------------------------------


def sim_recording(root: Path, seconds: float) -> Recording:
    root.mkdir(parents=True)
    runtime = RuntimeProcess(root, "sim", bundled_policy_path(), duration=seconds,
                             config=PATIENT)
    runtime.args += ["--record", str(root / "rec")]
    result = runtime.start().finish(timeout=seconds + 120)
    if result.returncode != 0:
        raise SystemExit(f"sim run failed ({result.returncode}): {result.stdout}{result.stderr}")
    return Recording.open(root / "rec")


# ---- 2. codecs -----------------------------------------------------------------------------


def encode_video(frames_bgr: list[np.ndarray], fourcc: str, suffix: str, directory: Path,
                 rate: float = RATE_HZ) -> tuple[float, float, Path]:
    """(CPU s, wall s, file) for writing ``frames_bgr`` through cv2.VideoWriter, open to
    release."""
    height, width = frames_bgr[0].shape[:2]
    path = directory / f"{fourcc.strip()}{suffix}"
    path.unlink(missing_ok=True)
    cpu, wall = time.process_time(), time.perf_counter()
    with stderr_silenced():  # FFmpeg's note on the WebM tag goes straight to descriptor 2
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), rate,
                                 (width, height))
    if not writer.isOpened():
        raise SystemExit(f"this OpenCV ({cv2.__version__}) cannot write {fourcc} {suffix}")
    for frame in frames_bgr:
        writer.write(frame)
    writer.release()
    return time.process_time() - cpu, time.perf_counter() - wall, path


def decode_video(path: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    frames: list[np.ndarray] = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    return frames


def encode_images(frames_bgr: list[np.ndarray], ext: str,
                  params: list[int]) -> tuple[float, float, list[bytes]]:
    cpu, wall = time.process_time(), time.perf_counter()
    encoded = []
    for frame in frames_bgr:
        ok, data = cv2.imencode(ext, frame, params)
        if not ok:
            raise SystemExit(f"cv2.imencode({ext}) failed")
        encoded.append(data.tobytes())
    return time.process_time() - cpu, time.perf_counter() - wall, encoded


def round_trip(name: str, frames_bgr: list[np.ndarray],
               directory: Path) -> tuple[float, float, int, list[np.ndarray]]:
    """(CPU s, wall s, bytes, decoded BGR frames) of one codec on ``frames_bgr``."""
    if name in VIDEO_CODECS:
        fourcc, suffix = VIDEO_CODECS[name]
        cpu, wall, path = encode_video(frames_bgr, fourcc, suffix, directory)
        size = path.stat().st_size
        decoded = decode_video(path)
        path.unlink()
        return cpu, wall, size, decoded
    ext, params = IMAGE_CODECS[name]
    cpu, wall, encoded = encode_images(frames_bgr, ext, params)
    decoded = [cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
               for data in encoded]
    return cpu, wall, sum(len(data) for data in encoded), decoded


def max_pixel_diff(original: list[np.ndarray], decoded: list[np.ndarray]) -> int | None:
    """The largest absolute difference of any pixel; None if the frame count differs."""
    if len(decoded) != len(original):
        return None
    return max(int(np.abs(a.astype(np.int16) - b.astype(np.int16)).max())
               for a, b in zip(original, decoded, strict=True))


def codec_table(sets: dict[str, list[np.ndarray]], rounds: int,
                directory: Path) -> dict[str, Any]:
    """Per frame set and codec: medians over ``rounds`` of CPU and wall ms per frame, bytes per
    frame, MB per minute at 30 Hz, and the largest pixel difference after decoding."""
    samples: dict[str, dict[str, dict[str, list[float]]]] = {
        set_name: {name: {"cpu_ms": [], "wall_ms": [], "bytes": []} for name in CODEC_NAMES}
        for set_name in sets}
    pixels: dict[str, dict[str, int | None]] = {set_name: {} for set_name in sets}
    for index in range(rounds):
        for set_name, frames_rgb in sets.items():
            frames_bgr = [np.ascontiguousarray(f[:, :, ::-1]) for f in frames_rgb]
            for name in rotated(CODEC_NAMES, index):
                cpu, wall, size, decoded = round_trip(name, frames_bgr, directory)
                count = len(frames_bgr)
                sample = samples[set_name][name]
                sample["cpu_ms"].append(cpu * 1e3 / count)
                sample["wall_ms"].append(wall * 1e3 / count)
                sample["bytes"].append(size / count)
                if index == 0:
                    pixels[set_name][name] = max_pixel_diff(frames_bgr, decoded)
        print(f"codecs: round {index + 1}/{rounds} done", flush=True)
    table: dict[str, Any] = {}
    for set_name, frames_rgb in sets.items():
        height, width = frames_rgb[0].shape[:2]
        raw = width * height * 3
        rows: dict[str, Any] = {"raw": {"bytes_per_frame": raw,
                                        "mb_per_min": round(raw * RATE_HZ * 60 / 1e6, 1),
                                        "max_pixel_diff": 0}}
        for name in CODEC_NAMES:
            sample = samples[set_name][name]
            size = median(sample["bytes"])
            rows[name] = {
                "cpu_ms_per_frame": round(median(sample["cpu_ms"]), 3),
                "wall_ms_per_frame": round(median(sample["wall_ms"]), 3),
                "bytes_per_frame": round(size),
                "mb_per_min": round(size * RATE_HZ * 60 / 1e6, 1),
                "max_pixel_diff": pixels[set_name][name],
                "cpu_ms_per_frame_rounds": [round(v, 3) for v in sample["cpu_ms"]],
            }
        base = rows["huffyuv"]
        for name in CODEC_NAMES:
            rows[name]["cpu_x_huffyuv"] = round(
                rows[name]["cpu_ms_per_frame"] / base["cpu_ms_per_frame"], 2)
            rows[name]["size_x_huffyuv"] = round(
                rows[name]["bytes_per_frame"] / base["bytes_per_frame"], 2)
        table[set_name] = {"size": [width, height], "frames": len(frames_rgb), "rows": rows}
    return table


# ---- 3. mu after a round trip --------------------------------------------------------------


def mu_round_trip(recording: Recording, directory: Path) -> dict[str, Any]:
    """Replay's ``mu`` differences (recorded against recomputed) on each codec's decoded frames;
    the baseline is the replay of the recording itself."""
    policy = OnnxPolicy.load(Path(recording.meta["policy"]["path"]), policy_config(recording))
    baseline = replay(recording, policy, threshold=1e-4)
    pairs = [(record, image) for record, image in recording.ticks_with_frames()
             if image is not None]
    recorded = np.array([record["mu"] for record, _ in pairs], dtype=np.float64)
    frames_bgr = [np.ascontiguousarray(image[:, :, ::-1]) for _, image in pairs]
    out: dict[str, Any] = {
        "ticks": len(pairs),
        "recorded_codec": recording.meta.get("codec"),
        "as_recorded": {key: baseline[key] for key in
                        ("mu_max_abs_diff", "mu_p99_abs_diff", "mu_mean_abs_diff")},
        "recorded_mu_abs_range": [round(float(np.abs(recorded).min()), 3),
                                  round(float(np.abs(recorded).max()), 3)],
    }
    for name in CODEC_NAMES:
        _, _, _, decoded = round_trip(name, frames_bgr, directory)
        if len(decoded) != len(frames_bgr):
            out[name] = {"error": f"{len(decoded)} frames decoded of {len(frames_bgr)}"}
            continue
        mu = np.array([policy.infer(np.ascontiguousarray(f[:, :, ::-1])) for f in decoded])
        diff = np.abs(mu - recorded).max(axis=1)
        out[name] = {"mu_max_abs_diff": float(diff.max()),
                     "mu_p99_abs_diff": float(np.percentile(diff, 99)),
                     "mu_mean_abs_diff": float(diff.mean()),
                     "max_pixel_diff": max_pixel_diff(frames_bgr, decoded)}
    return out


# ---- 4. the report's video -----------------------------------------------------------------


def report_codecs(recording: Recording, count: int, rounds: int,
                  directory: Path) -> dict[str, Any]:
    """mp4v against VP9 on ``count`` of ``report``'s own frames, medians over ``rounds``."""
    max_speed = float(recording.meta.get("max_speed") or 1.0)
    frames = [compose(image, record, max_speed, None)
              for record, image in recording.ticks_with_frames() if image is not None][:count]
    samples: dict[str, dict[str, list[float]]] = {
        name: {"cpu_ms": [], "wall_ms": [], "bytes": []} for name in REPORT_CODECS}
    for index in range(rounds):
        for name in rotated(list(REPORT_CODECS), index):
            fourcc, suffix = REPORT_CODECS[name]
            cpu, wall, path = encode_video(frames, fourcc, suffix, directory)
            samples[name]["cpu_ms"].append(cpu * 1e3 / len(frames))
            samples[name]["wall_ms"].append(wall * 1e3 / len(frames))
            samples[name]["bytes"].append(path.stat().st_size / len(frames))
            path.unlink()
    height, width = frames[0].shape[:2]
    out: dict[str, Any] = {"size": [width, height], "frames": len(frames), "rounds": rounds}
    for name, sample in samples.items():
        out[name] = {"cpu_ms_per_frame": round(median(sample["cpu_ms"]), 3),
                     "wall_ms_per_frame": round(median(sample["wall_ms"]), 3),
                     "bytes_per_frame": round(median(sample["bytes"])),
                     "cpu_ms_per_frame_rounds": [round(v, 3) for v in sample["cpu_ms"]]}
    out["vp9_cpu_x_mp4v"] = round(out["vp9"]["cpu_ms_per_frame"]
                                  / out["mp4v"]["cpu_ms_per_frame"], 1)
    out["vp9_wall_x_mp4v"] = round(out["vp9"]["wall_ms_per_frame"]
                                   / out["mp4v"]["wall_ms_per_frame"], 1)
    return out


# ---- 5. the loop ---------------------------------------------------------------------------


def loop_runs(root: Path, rounds: int, seconds: float) -> dict[str, Any]:
    runs: list[dict[str, Any]] = []
    names = list(LOOP_VARIANTS)
    for index in range(rounds):
        for name in rotated(names, index):
            record, extra = LOOP_VARIANTS[name]
            run = one_run(root / f"{index}-{name}", "real", seconds, record, "photo", extra)
            run["variant"], run["round"] = name, index
            runs.append(run)
            print(f"loop: {name} round {index + 1}/{rounds}: p99 late {run['late_ms_p99']} ms, "
                  f"overruns {run['overruns']}, load {run['load_1min_before']}", flush=True)
    summary: dict[str, Any] = {"seconds_per_run": seconds, "rounds": rounds,
                               "camera": "photo", "backend": "real"}
    minutes = seconds / 60.0
    for name in names:
        mine = [r for r in runs if r["variant"] == name]
        row: dict[str, Any] = {
            "late_ms_p99": round(median([r["late_ms_p99"] for r in mine]), 3),
            "tick_ms_p99": round(median([r["tick_ms_p99"] for r in mine]), 3),
            "overruns_median": median([r["overruns"] for r in mine]),
            "overruns_total": sum(r["overruns"] for r in mine),
            "ticks_total": sum(r["ticks"] for r in mine),
            "expected_ticks_total": sum(r["expected_ticks"] for r in mine),
            "cpu_s_per_min": round(median([r["cpu_s"] for r in mine]) / minutes, 2),
        }
        if LOOP_VARIANTS[name][0]:
            row.update(frames_dropped=sum(r["frames_dropped"] for r in mine),
                       records_lost=sum(r["records_lost"] for r in mine),
                       disk_mb_per_min=round(median([r["disk_bytes"] for r in mine])
                                             / 1e6 / minutes, 2),
                       codecs=sorted({str(r["codec"]) for r in mine}))
        summary[name] = row
    base = summary["without"]["late_ms_p99"]
    for name in names:
        summary[name]["late_p99_x_without"] = round(summary[name]["late_ms_p99"] / base, 2) \
            if base else None
    summary["runs"] = runs
    return summary


# ---- the results ---------------------------------------------------------------------------


def ms(value: float) -> str:
    return f"{value:.3g} ms" if value < 10 else f"{value:.1f} ms"


def kb(value: float) -> str:
    return f"{value / 1e3:.1f} KB" if value < 1e4 else f"{value / 1e3:.0f} KB"


def markdown(result: dict[str, Any]) -> str:
    machine = result["machine"]
    lines = [
        "# Recording codecs and the writer, re-measured", "",
        f"Command: `{result['command']}`  ",
        f"Machine: {machine['cpu']}, {machine['cores']} cores, Python {machine['python']}, "
        f"OpenCV {machine['opencv']}; 1-min load average {machine['loadavg_1min_at_start']} at "
        f"start, {machine['loadavg_1min_at_end']} at the end (other jobs shared the cores)  ",
        f"Date: {result['date']}; the benchmark took {result['wall_s']:.0f} s; versions in "
        "record_codecs.json. Variants interleaved in rounds (order rotated each round); "
        "medians over rounds.", "",
        "## 1. Codecs: CPU and size per frame", "",
        f"{result['codec_rounds']} rounds of {result['frames_per_set']} frames per set. CPU: the "
        "process's (all threads), open to release, per frame; MB per minute at 30 Hz; "
        "pixel diff: the largest absolute difference of any pixel after decoding (0: lossless). "
        "x HuffYUV: CPU / size against HuffYUV's in the same set.", "",
    ]
    for set_name, table in result["codecs"].items():
        width, height = table["size"]
        lines += [f"### {set_name} ({width}x{height})", "",
                  "| codec | CPU per frame | wall per frame | size per frame | at 30 Hz | "
                  "pixel diff | CPU x HuffYUV | size x HuffYUV |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for name, row in table["rows"].items():
            if name == "raw":
                lines.append(f"| {LABELS[name]} | | | {kb(row['bytes_per_frame'])} | "
                             f"{row['mb_per_min']} MB/min | 0 | | |")
                continue
            lines.append(
                f"| {LABELS[name]} | {ms(row['cpu_ms_per_frame'])} | "
                f"{ms(row['wall_ms_per_frame'])} | {kb(row['bytes_per_frame'])} | "
                f"{row['mb_per_min']} MB/min | {row['max_pixel_diff']} | "
                f"x{row['cpu_x_huffyuv']} | x{row['size_x_huffyuv']} |")
        lines.append("")
    mu = result["mu"]
    low, high = mu["recorded_mu_abs_range"]
    lines += [
        "## 2. The policy's mu after a decode round trip", "",
        f"The sim run's {mu['ticks']} recorded frames ({mu['recorded_codec']}) through each "
        "codec, the bundled policy on the decoded frames (replay's policy and [policy] "
        "settings) against the mu it recorded while driving: |mu - recorded mu| over ticks, "
        f"the larger wheel (recorded |mu| {low}-{high}). Baseline: `jetbot-rt replay` of "
        "the recording as written.", "",
        "| frames | max abs diff | p99 | mean | pixel diff |", "| --- | --- | --- | --- | --- |",
        f"| as recorded (replay) | {mu['as_recorded']['mu_max_abs_diff']:.3g} | "
        f"{mu['as_recorded']['mu_p99_abs_diff']:.3g} | "
        f"{mu['as_recorded']['mu_mean_abs_diff']:.3g} | 0 |",
    ]
    for name in CODEC_NAMES:
        row = mu[name]
        if "error" in row:
            lines.append(f"| {LABELS[name]} | {row['error']} | | | |")
            continue
        lines.append(f"| {LABELS[name]} | {row['mu_max_abs_diff']:.3g} | "
                     f"{row['mu_p99_abs_diff']:.3g} | {row['mu_mean_abs_diff']:.3g} | "
                     f"{row['max_pixel_diff']} |")
    report = result["report"]
    width, height = report["size"]
    lines += [
        "", "## 3. The report's video: mp4v against VP9", "",
        f"{report['frames']} of `report`'s own frames ({width}x{height}: the 56x56 frame "
        f"enlarged 8x and the panel), {report['rounds']} rounds.", "",
        "| codec | CPU per frame | wall per frame | size per frame |", "| --- | --- | --- | --- |",
    ]
    for name in REPORT_CODECS:
        row = report[name]
        lines.append(f"| {name} | {ms(row['cpu_ms_per_frame'])} | "
                     f"{ms(row['wall_ms_per_frame'])} | {kb(row['bytes_per_frame'])} |")
    lines += ["", f"VP9 / mp4v: x{report['vp9_cpu_x_mp4v']} CPU, x{report['vp9_wall_x_mp4v']} "
              "wall time per frame.", ""]
    loop = result["loop"]
    lines += [
        "## 4. The control loop: without recording, recording HuffYUV, recording FFV1", "",
        f"`jetbot-rt run --backend real` at 30 Hz (emulated board, the photo as a live "
        f"GStreamer camera, the bundled policy: 56x56 frames), {loop['seconds_per_run']:g} s "
        f"per run, {loop['rounds']} rounds. Medians of the runs' figures; overruns: median "
        "per run (total).", "",
        "| | tick-start jitter p99 | x without | p99 per run | tick time p99 | overruns | "
        "ticks / expected | CPU per minute | disk | frames dropped |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name in LOOP_VARIANTS:
        row = loop[name]
        disk = f"{row['disk_mb_per_min']} MB/min" if "disk_mb_per_min" in row else ""
        dropped = row.get("frames_dropped", "")
        per_run = ", ".join(f"{r['late_ms_p99']:.3g}" for r in loop["runs"]
                            if r["variant"] == name)
        lines.append(
            f"| {name} | {ms(row['late_ms_p99'])} | x{row['late_p99_x_without']} | "
            f"{per_run} ms | {ms(row['tick_ms_p99'])} | "
            f"{row['overruns_median']:g} ({row['overruns_total']}) | "
            f"{row['ticks_total']} / {row['expected_ticks_total']} | "
            f"{row['cpu_s_per_min']} s | {disk} | {dropped} |")
    loads = [r["load_1min_before"] for r in loop["runs"]]
    lines += ["", f"1-min load before each run, in order: {loads}.", "",
              "## Not measured", "", result["not_measured"], ""]
    return "\n".join(lines)


def timed(label: str, step: Callable[[], Any]) -> Any:
    began = time.perf_counter()
    value = step()
    print(f"{label}: {time.perf_counter() - began:.0f} s", flush=True)
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="codec rounds (default 5)")
    parser.add_argument("--frames", type=int, default=300,
                        help="frames per set and codec in a round (default 300: 10 s)")
    parser.add_argument("--report-frames", type=int, default=60)
    parser.add_argument("--loop-rounds", type=int, default=3)
    parser.add_argument("--loop-seconds", type=float, default=20.0)
    parser.add_argument("--sim-seconds", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    began = time.perf_counter()
    machine = {"cpu": cpu_model(), "cores": os.cpu_count(), "machine": platform.machine(),
               "python": platform.python_version(), "opencv": cv2.__version__,
               "loadavg_1min_at_start": round(os.getloadavg()[0], 2)}
    result: dict[str, Any] = {
        **run_record(),
        "machine": machine,
    }
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        recording = timed("sim recording", lambda: sim_recording(root / "sim", args.sim_seconds))
        sim_frames = [image for _, image in recording.ticks_with_frames() if image is not None]
        repeats = -(-args.frames // len(sim_frames))
        portrait = photo()
        sets = {
            "sim frames, the bundled policy's input": (sim_frames * repeats)[:args.frames],
            "photo, the bundled policy's input": [fitted(portrait, 56)] * args.frames,
            "photo, a 224x224 policy's input": [fitted(portrait, 224)] * args.frames,
        }
        work = root / "codecs"
        work.mkdir()
        result["frames_per_set"] = args.frames
        result["codec_rounds"] = args.rounds
        result["codecs"] = timed("codecs", lambda: codec_table(sets, args.rounds, work))
        result["mu"] = timed("mu", lambda: mu_round_trip(recording, work))
        result["report"] = timed("report codecs", lambda: report_codecs(
            recording, args.report_frames, args.rounds, work))
        result["loop"] = timed("loop", lambda: loop_runs(root / "loop", args.loop_rounds,
                                                         args.loop_seconds))
    result["not_measured"] = (
        "The writer thread that the writer process replaced (a nice-19 thread handing over "
        "through `queue.Queue`, then lock-free) was removed in 82dd2c2; no switch brings it "
        "back, so its jitter and overruns against the process are not re-measured here.")
    machine["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    result["wall_s"] = round(time.perf_counter() - began, 1)
    write_results(args.out, "record_codecs", result, markdown(result))


if __name__ == "__main__":
    main()
