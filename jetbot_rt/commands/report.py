"""``jetbot-rt report DIR``: look at a run. Writes ``run.mp4`` (the frames at their real pace
with mu, duties and the tick's state drawn on them, a marker where the run stopped: red for a
fault, grey for an end it chose) and ``run.png`` (mu, duties, tick time, frame age, overruns,
faults and takeovers on one time axis; for a sim run, the path seen from above with the goal)
beside the recording, and prints the summary. On a bare telemetry JSONL file it writes
``<name>.png`` only. The video is H.264 where this OpenCV's FFmpeg has an encoder for it (pip's
wheels have none), else MPEG-4 Part 2 (mp4v), and the output line says which.

The recording is untrusted (``recording/reader.py`` validates it) and so is the directory it
sits in: each output is written to a new file created without following links and renamed into place
once complete (``safe_file.replaced_file``), so a ``run.png`` planted as a link to another file
is replaced, not written through. The video is bounded by the ticks: a pause longer than
``MAX_GAP_S`` is shortened, and it stops at ``MAX_VIDEO_FRAMES``. An output that cannot be
written (a full disk) is one line and exit 1: the recording was fine, the report was not made.

matplotlib is imported only here, and only for the plot; the robot may not have it.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import shown
from jetbot_rt.errors import EXIT_OK, UsageError
from jetbot_rt.recording.reader import Recording
from jetbot_rt.teleop.hand import HUMAN

DISPLAY_WIDTH = 448  # frames are enlarged by a whole factor to about this width (56 px by 8)
PANEL = 120  # px of text and bars under the frame
STOP_HOLD_S = 1.5  # the last frame with the stop marker stays this long at the end
MAX_GAP_S = 10.0
"""A pause between two ticks is shown at most this long: the longest a run can pause without
its watchdog stopping it (``[loop] watchdog_timeout`` is at most 10 s)."""
MAX_VIDEO_FRAMES = 108_000
"""An hour at 30 Hz (a few GB of mp4v at most): the video stops there, saying so."""
DISPLAY_LIMIT = 1e6
"""mu is plotted clipped to this: a finite but huge value would overflow the axis range."""
EXIT_NOT_WRITTEN = 1
"""An output could not be written (disk full, no permission): not bad input (2)."""
CODECS = (("avc1", "H.264"), ("mp4v", "mp4v"))
"""Tried in this order. VP9 (vp09) plays in browsers too and pip's OpenCV has it, but it took
22 times mp4v's CPU a frame (``benchmarks/bench_record_codecs.py``)."""
NO_H264 = ("this OpenCV's FFmpeg has no H.264 encoder, so browsers may not play it; "
           "`ffmpeg -i run.mp4 -c:v libx264 -pix_fmt yuv420p run-h264.mp4` converts it")
FAULT_COLOR, ORDERLY_COLOR, HUMAN_COLOR = "tab:red", "tab:gray", "tab:purple"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", metavar="DIR",
                        help="a directory written by run --record, or a --telemetry JSONL file")
    parser.add_argument("--out", metavar="DIR",
                        help="where to write run.mp4 / run.png (default: beside the input)")
    parser.add_argument("--no-video", action="store_true", help="write the plot only")


# ---- summary -------------------------------------------------------------------------------


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def summarize(recording: Recording) -> dict[str, Any]:
    ticks = recording.ticks
    times = [r["t"] for r in ticks]
    duration = times[-1] - times[0] if len(times) > 1 else 0.0
    stops = [e for e in recording.events if e["event"] == "safe_stop"]
    ends = [e for e in recording.events if e["event"] == "end"]
    summary: dict[str, Any] = {
        "ticks": len(ticks),
        "duration_s": round(duration, 3),
        "rate_hz": round((len(ticks) - 1) / duration, 2) if duration > 0 else 0.0,
        "tick_ms_p50": round(_percentile([r["tick_ms"] for r in ticks], 50), 3),
        "tick_ms_p99": round(_percentile([r["tick_ms"] for r in ticks], 99), 3),
        "frame_age_ms_p99": round(_percentile([r["frame_age_ms"] for r in ticks], 99), 3),
        "overruns": ticks[-1]["overruns"] if ticks else 0,
        "frames_missing": sum(1 for r in ticks if r.get("frame", 0) is None),
        "stopped": stops[0].get("reason") if stops else (ends[0].get("reason") if ends else None),
        "fault": bool(stops[0].get("fault")) if stops else None,
    }
    if recording.summary:
        summary["frames_dropped"] = recording.summary.get("frames_dropped", 0)
        if recording.summary.get("error"):
            summary["recording_error"] = recording.summary["error"]
    return summary


def print_summary(recording: Recording, summary: dict[str, Any]) -> None:
    meta = recording.meta
    lines = [f"jetbot-rt report: {recording.path}"]
    if meta:
        lines.append(f"  backend      {meta.get('backend')}, policy "
                     f"{meta.get('policy', {}).get('path')}")
    lines += [
        f"  ticks        {summary['ticks']} in {summary['duration_s']:.2f} s "
        f"({summary['rate_hz']:.2f} Hz)",
        f"  tick time    p50 {summary['tick_ms_p50']:.2f} ms, p99 {summary['tick_ms_p99']:.2f} ms",
        f"  frame age    p99 {summary['frame_age_ms_p99']:.1f} ms",
        f"  overruns     {summary['overruns']}",
    ]
    if meta:
        lines.append(f"  frames       {summary['frames_missing']} ticks without a frame")
    if summary.get("recording_error"):
        lines.append(f"  recording    stopped: {summary['recording_error']}")
    if summary["stopped"]:
        kind = "fault" if summary["fault"] else "orderly"
        lines.append(f"  stopped      {summary['stopped']} ({kind})")
    print("\n".join(lines), flush=True)


# ---- plot ----------------------------------------------------------------------------------


def plot(recording: Recording, out_dir: Path, name: str) -> bool:
    """``out_dir/name`` (a PNG); False (and one line on stderr) when matplotlib is not
    installed. ``OSError`` when it cannot be written."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
    except ImportError:
        print("jetbot-rt report: the plot needs matplotlib: pip install 'jetbot_rt[train]'",
              file=sys.stderr)
        return False
    ticks = recording.ticks
    t = np.array([r["t"] for r in ticks])
    column = {key: np.array([r[key] for r in ticks], dtype=float)
              for key in ("tick_ms", "infer_ms", "frame_age_ms", "overruns")}
    mu = np.clip(np.array([r["mu"] for r in ticks], dtype=float).reshape(-1, 2),
                 -DISPLAY_LIMIT, DISPLAY_LIMIT)
    cmd = np.array([r["cmd"] for r in ticks], dtype=float).reshape(-1, 2)
    path = positions(ticks)
    fig = plt.figure(figsize=(17 if path is not None else 12, 10))
    grid = fig.add_gridspec(5, 2 if path is not None else 1, height_ratios=[2, 2, 2, 1.5, 1],
                            width_ratios=[3, 1.35] if path is not None else [1])
    axes = [fig.add_subplot(grid[0, 0])]
    axes += [fig.add_subplot(grid[row, 0], sharex=axes[0]) for row in range(1, 5)]
    for axis in axes[:-1]:
        axis.tick_params(labelbottom=False)
    rows = [
        (axes[0], [(mu[:, 0], "mu left"), (mu[:, 1], "mu right")], "mu"),
        (axes[1], [(cmd[:, 0], "duty left"), (cmd[:, 1], "duty right")], "duty"),
        (axes[2], [(column["tick_ms"], "tick"), (column["infer_ms"], "inference")], "ms"),
        (axes[3], [(column["frame_age_ms"], "frame age")], "frame age ms"),
        (axes[4], [(column["overruns"], "overruns (total)")], "overruns"),
    ]
    for axis, series, label in rows:
        for values, legend in series:
            axis.step(t, values, where="post", label=legend, linewidth=1)
        axis.set_ylabel(label)
        axis.grid(alpha=0.3)
        axis.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8)
    if recording.meta.get("rate_hz"):
        axes[2].axhline(1e3 / float(recording.meta["rate_hz"]), color="black", linewidth=0.8,
                        linestyle=":", label="period")
        axes[2].legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8)
    missing = [r["t"] for r in ticks if "frame" in r and r["frame"] is None]
    if missing:
        axes[3].plot(missing, [0] * len(missing), "|", color="tab:red", label="frame dropped")
        axes[3].legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8)
    spans = human_spans(recording)
    for start, end in spans:
        for axis in axes:
            axis.axvspan(start, end, color=HUMAN_COLOR, alpha=0.12, linewidth=0)
    if spans:
        axes[0].plot([], [], color=HUMAN_COLOR, alpha=0.4, linewidth=6,
                     label=f"a person drives ({len(spans)}x)")
        axes[0].legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8)
    for event in recording.events:
        if event["event"] in ("start", "end") or event["event"] in TAKEOVER_EVENTS:
            continue
        color = event_color(event)
        for axis in axes:
            axis.axvline(event["t"], color=color, linestyle="--", linewidth=1)
        axes[0].annotate(f"{event_label(event)}: {event.get('reason', '')}"[:70],
                         (event["t"], 1.0), xycoords=("data", "axes fraction"),
                         xytext=(-4, -4), textcoords="offset points", ha="right", va="top",
                         fontsize=8, color=color,
                         bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"})
    if path is not None:
        draw_map(fig.add_subplot(grid[:, 1]), recording, path, spans)
    axes[4].yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(nbins=4, integer=True))
    axes[-1].set_xlabel("t (s)")
    title = str(recording.path)
    if recording.meta:
        title += (f"  |  {recording.meta.get('backend')}, "
                  f"{Path(recording.meta.get('policy', {}).get('path') or '?').name}")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    try:
        with safe_file.replaced_file(out_dir, name) as fd, os.fdopen(os.dup(fd), "wb") as file:
            fig.savefig(file, format="png", dpi=100)
    finally:
        plt.close(fig)
    return True


TAKEOVER_EVENTS = ("takeover", "handback")


def is_fault(event: dict[str, Any]) -> bool:
    """A safe stop after a fault; an event without ``fault`` is none (a takeover, a note)."""
    return bool(event.get("fault", False))


def event_color(event: dict[str, Any]) -> str:
    return FAULT_COLOR if is_fault(event) else ORDERLY_COLOR


def event_label(event: dict[str, Any]) -> str:
    if event["event"] == "safe_stop":
        return "fault, safe stop" if is_fault(event) else "stopped"
    return str(event["event"])


def human_spans(recording: Recording) -> list[tuple[float, float]]:
    """(start, end) times while a person drove: from the ticks' ``driver`` where recorded,
    else from ``takeover``/``handback`` events; none in a recording that has neither."""
    ticks = recording.ticks
    spans: list[tuple[float, float]] = []
    start: float | None = None
    if any("driver" in r for r in ticks):
        for record in ticks:
            human = record.get("driver") == HUMAN
            if human and start is None:
                start = record["t"]
            elif not human and start is not None:
                spans.append((start, record["t"]))
                start = None
    else:
        for event in sorted(recording.events, key=lambda e: e["t"]):
            if event["event"] == "takeover" and start is None:
                start = event["t"]
            elif event["event"] == "handback" and start is not None:
                spans.append((start, event["t"]))
                start = None
    if start is not None and ticks:
        spans.append((start, ticks[-1]["t"]))
    return spans


def positions(ticks: list[dict[str, Any]]) -> np.ndarray | None:
    """The recorded (t, x, y) of the ticks that have a ``pose`` (the sim's), or None."""
    rows = [(r["t"], r["pose"][0], r["pose"][1]) for r in ticks if "pose" in r]
    return np.array(rows, dtype=float) if len(rows) >= 2 else None


def draw_map(axis: Any, recording: Recording, path: np.ndarray,
             spans: list[tuple[float, float]]) -> None:
    """The path seen from above (x forward at the start, y left), the goal where the sim
    state has one, where a person drove, and where the run stopped."""
    t, x, y = path[:, 0], path[:, 1], path[:, 2]
    axis.plot(x, y, color="tab:blue", linewidth=1.5, label="path")
    for index, (start, end) in enumerate(spans):
        inside = (t >= start) & (t <= end)
        axis.plot(x[inside], y[inside], color=HUMAN_COLOR, linewidth=4, alpha=0.6,
                  label="a person drives" if index == 0 else None)
    axis.plot(x[0], y[0], "o", color="tab:green", markersize=8, label="start")
    goals = [r["goal"] for r in recording.ticks if "goal" in r]
    extent = [x, y]
    if goals:
        goal = np.array(goals[-1], dtype=float)
        axis.plot(goal[0], goal[1], "s", color="tab:red", markersize=10, label="goal")
        extent = [np.append(x, goal[0]), np.append(y, goal[1])]
    stops = [e for e in recording.events if e["event"] == "safe_stop"]
    if stops:
        color = event_color(stops[0])
        axis.plot(x[-1], y[-1], "X", color=color, markersize=11,
                  label=event_label(stops[0]))
    else:
        axis.plot(x[-1], y[-1], "X", color="black", markersize=9, label="end")
    # a square of the path and the goal, equal scales: a turn looks like the turn it was
    half = max(np.ptp(extent[0]), np.ptp(extent[1])) / 2 + 0.15
    centre = [(values.min() + values.max()) / 2 for values in extent]
    axis.set_xlim(centre[0] - half, centre[0] + half)
    axis.set_ylim(centre[1] - half, centre[1] + half)
    axis.set_aspect("equal", adjustable="box")
    axis.set_xlabel("x (m)")
    axis.set_ylabel("y (m)")
    axis.set_title("from above", fontsize=10)
    axis.grid(alpha=0.3)
    axis.legend(loc="best", fontsize=8)


# ---- video ---------------------------------------------------------------------------------


def _bar(canvas: np.ndarray, x: int, y: int, value: float, label: str,
         scale: float = 1.0) -> None:
    """A horizontal bar for ``value / scale`` in [-1, 1] around a centre line."""
    width = 150
    cv2.putText(canvas, label, (x, y + 11), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (220, 220, 220), 1)
    left = x + 50
    cv2.rectangle(canvas, (left, y), (left + width, y + 12), (80, 80, 80), 1)
    centre = left + width // 2
    end = centre + int(max(-1.0, min(1.0, value / scale)) * width / 2)
    color = (80, 200, 80) if value >= 0 else (80, 80, 230)
    cv2.rectangle(canvas, (min(centre, end), y + 2), (max(centre, end), y + 10), color, -1)
    cv2.putText(canvas, f"{value:+.3f}", (left + width + 6, y + 11), cv2.FONT_HERSHEY_SIMPLEX,
                0.4, (220, 220, 220), 1)


def compose(image: np.ndarray, record: dict[str, Any], max_speed: float,
            stop: dict[str, Any] | None) -> np.ndarray:
    """One video frame (BGR): the frame enlarged, and a panel with the tick's numbers."""
    scale = max(1, round(DISPLAY_WIDTH / image.shape[1]))
    height, width = image.shape[0] * scale, image.shape[1] * scale
    canvas = np.zeros((height + PANEL, width, 3), np.uint8)
    canvas[:height] = cv2.resize(image[:, :, ::-1], (width, height),
                                 interpolation=cv2.INTER_NEAREST)
    white = (230, 230, 230)
    fault = stop is not None and is_fault(stop)
    state = str(record.get("state") or "")[:24]
    if record.get("driver") == HUMAN:
        state += " (a person drives)"
    text = (f"t {record['t']:7.2f} s  tick {record['tick']}  "
            f"{('SAFE STOP' if fault else 'STOPPED') if stop else state}")
    cv2.putText(canvas, text, (6, height + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, white, 1)
    mu, cmd = record["mu"], ((stop.get("cmd") or [0.0, 0.0]) if stop else record["cmd"])
    _bar(canvas, 6, height + 26, mu[0], "mu L")
    _bar(canvas, 6, height + 44, mu[1], "mu R")
    _bar(canvas, 6, height + 66, cmd[0], "duty L", max_speed)
    _bar(canvas, 6, height + 84, cmd[1], "duty R", max_speed)
    timing = (f"tick {record['tick_ms']:.1f} ms  infer {record['infer_ms']:.1f} ms  "
              f"age {record['frame_age_ms']:.0f} ms  overruns {record['overruns']}")
    cv2.putText(canvas, timing, (6, height + PANEL - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4, white, 1)
    if record.get("frame", 0) is None:
        cv2.putText(canvas, "frame dropped: previous shown", (6, 20),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 200, 255), 1)
    if stop:
        # red for a fault; an end the run chose (a duration, a signal, `jetbot-rt stop`) grey
        color = (0, 0, 255) if fault else (200, 200, 200)
        cv2.rectangle(canvas, (0, 0), (width - 1, height - 1), color, 6)
        cv2.putText(canvas, "SAFE STOP" if fault else "STOPPED", (12, 40),
                    cv2.FONT_HERSHEY_SIMPLEX, 1.0, color, 2)
        cv2.putText(canvas, str(stop.get("reason", ""))[:48], (12, 64),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, color, 1)
    return canvas


class Video:
    """run.mp4 at the recording's rate; a video frame shows the newest tick at its time, so
    overruns and pauses last as long as they did (a pause at most ``MAX_GAP_S``), up to
    ``MAX_VIDEO_FRAMES``."""

    def __init__(self, recording: Recording) -> None:
        meta = recording.meta
        self.recording = recording
        self.fps = float(meta["rate_hz"])
        self.max_speed = float(meta.get("max_speed") or 0.1)
        stops = [e for e in recording.events if e["event"] == "safe_stop"]
        self.stop = stops[0] if stops else None
        self.writer: Any = None
        self.written = 0
        self.first: float | None = None  # the shown time of the first video frame
        self.shortened = 0  # pauses shortened to MAX_GAP_S
        self.cut = False  # stopped at MAX_VIDEO_FRAMES
        self.codec = ""  # what the video is: H.264 or mp4v

    def write(self, out_dir: Path, name: str) -> bool:
        """False when no tick has a frame (nothing written); ``OSError`` when the file cannot
        be written, or turns out incomplete."""
        try:
            with safe_file.replaced_file(out_dir, name) as fd:
                with safe_file.path_for_library(fd, ".mp4") as path:
                    try:
                        self._frames(path, fd)
                    finally:
                        if self.writer is not None:
                            self.writer.release()
                if not self.written:
                    raise _NothingToShow
                if not mp4_complete(fd):
                    raise OSError(errno.EIO, "the file came out incomplete (disk full?)")
        except _NothingToShow:
            return False
        return True

    def _frames(self, path: str, fd: int) -> None:
        offset = 0.0  # time cut out of long pauses so far
        last: tuple[np.ndarray, dict[str, Any]] | None = None
        for record, image in self.recording.ticks_with_frames():
            if image is None and last is not None:
                image = last[0]
            if image is None:
                continue
            if last is not None and record["t"] - last[1]["t"] > MAX_GAP_S:
                offset += record["t"] - last[1]["t"] - MAX_GAP_S
                self.shortened += 1
            shown_t = record["t"] - offset
            if self.first is None:
                self.first = shown_t
            if last is not None:
                self._emit(path, fd, last[0], last[1], shown_t, False)
            last = (image, record)
            if self.cut:
                return
        if last is not None:
            end = last[1]["t"] - offset + 1.0 / self.fps
            self._emit(path, fd, last[0], last[1], end, False)
            if self.stop is not None:
                self._emit(path, fd, last[0], last[1], self._slot() + STOP_HOLD_S, True)

    def _slot(self) -> float:
        assert self.first is not None
        return self.first + self.written / self.fps

    def _emit(self, path: str, fd: int, image: np.ndarray, record: dict[str, Any],
              until: float, marked: bool) -> None:
        frame = compose(image, record, self.max_speed, self.stop if marked else None)
        if self.writer is None:
            self.writer, self.codec = open_writer(path, self.fps,
                                                  (frame.shape[1], frame.shape[0]))
        while self._slot() < until:
            if self.written >= MAX_VIDEO_FRAMES:
                self.cut = True
                return
            if self.written % 256 == 0:
                disk = os.fstatvfs(fd)  # the video writer does not report a full disk
                if disk.f_bavail * disk.f_frsize < MIN_FREE_BYTES:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            self.writer.write(frame)
            self.written += 1


def open_writer(path: str, fps: float, size: tuple[int, int]) -> tuple[Any, str]:
    """The first of ``CODECS`` this OpenCV can write (the probe is opening it: an FFmpeg
    without the encoder refuses), and its name. OpenCV's and FFmpeg's complaints about a
    missing encoder (FFmpeg's go straight to file descriptor 2) are silenced: the output line
    says which codec it is."""
    for fourcc, name in CODECS:
        with stderr_silenced():
            writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*fourcc), fps, size)
        if writer.isOpened():
            return writer, name
        writer.release()
    raise OSError(errno.EIO, "OpenCV cannot write H.264 or mp4v video here")


MIN_FREE_BYTES = 4 * 1024 * 1024
"""Less free space than this on the video's file system stops the video (ENOSPC)."""


class _NothingToShow(Exception):
    """No tick has a frame: the video is not made."""


def mp4_complete(fd: int) -> bool:
    """The MP4's top-level boxes tile the file exactly and include ``moov`` (written when the
    writer is released): a write that failed on the way leaves it out or cut."""
    size = os.fstat(fd).st_size
    offset = 0
    found = False
    while offset < size:
        header = os.pread(fd, 16, offset)
        length = int.from_bytes(header[:4], "big") if len(header) >= 8 else 0
        if length == 1 and len(header) == 16:
            length = int.from_bytes(header[8:16], "big")
        elif length == 0 and len(header) >= 8:
            length = size - offset
        if length < 8:
            return False
        found = found or header[4:8] == b"moov"
        offset += length
    return found and offset == size


@contextlib.contextmanager
def stderr_silenced() -> Iterator[None]:
    """File descriptor 2 to /dev/null for a moment (the report is one thread: nothing of
    ours is lost)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        null = os.open(os.devnull, os.O_WRONLY | os.O_CLOEXEC)
        try:
            os.dup2(null, 2)
        finally:
            os.close(null)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


@contextlib.contextmanager
def quiet_opencv() -> Iterator[None]:
    """OpenCV's video writer warns once per frame it cannot write; the failure is reported
    once, by ``Video.write``."""
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is None:
        yield
        return
    level = logging.getLogLevel()
    logging.setLogLevel(logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        logging.setLogLevel(level)


def run(args: argparse.Namespace) -> int:
    recording = Recording.open(args.recording)
    if not recording.ticks:
        raise UsageError(f"{shown(args.recording)}: no tick records in it")
    is_dir = bool(recording.meta)
    out_dir = Path(args.out) if args.out else (recording.path if is_dir else recording.path.parent)
    safe_file.text_path(out_dir, "--out")
    png = "run.png" if is_dir else recording.path.stem + ".png"
    summary = summarize(recording)
    print_summary(recording, summary)
    target = out_dir
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        target = out_dir / png
        if plot(recording, out_dir, png):
            print(f"wrote {target}", flush=True)
        if is_dir and not args.no_video:
            target = out_dir / "run.mp4"
            video = Video(recording)
            with quiet_opencv():
                made = video.write(out_dir, "run.mp4")
            if not made:
                print(f"no frames to show: {target} not written", flush=True)
                return EXIT_OK
            notes = "".join([
                f"; {video.shortened} pauses over {MAX_GAP_S:g} s shortened to it"
                if video.shortened else "",
                f"; cut at {MAX_VIDEO_FRAMES} frames" if video.cut else ""])
            print(f"wrote {target} ({video.written} frames, {video.written / video.fps:.1f} s"
                  f"{notes})", flush=True)
            print("video: H.264" if video.codec == "H.264"
                  else f"note: {target.name} is MPEG-4 Part 2 (mp4v): {NO_H264}", flush=True)
    except OSError as exc:
        print(f"jetbot-rt report: error: cannot write {shown(target)}: "
              f"{exc.strerror or exc}", file=sys.stderr, flush=True)
        return EXIT_NOT_WRITTEN
    return EXIT_OK
