"""``jetbot-rt replay DIR``: run a policy offline over a recording's frames and compare its
``mu`` with the recorded one, tick by tick.

With the recording's own policy the difference is round-off (the frames are stored lossless);
with another policy it says what that policy would have done on these very frames, before it
ever drives. Replay opens no motor board and no camera: it imports neither.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from jetbot_rt.config.safe_file import shown
from jetbot_rt.config.schema import set_value
from jetbot_rt.config.sections import PolicyConfig
from jetbot_rt.errors import EXIT_OK, UsageError
from jetbot_rt.recording.reader import Recording
from jetbot_rt.recording.recorder import sha256_of
from jetbot_rt.runtime.policy import OnnxPolicy


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", metavar="DIR", help="a directory written by run --record")
    parser.add_argument("--policy", help="ONNX policy to replay (default: the recorded one)")
    parser.add_argument("--threshold", type=float, default=1e-4,
                        help="|mu difference| above which a tick is printed (default 1e-4; "
                             "0: every tick that differs at all); --json prints every tick")
    parser.add_argument("--json", action="store_true",
                        help="a JSON line per tick (every tick: data for a program) and the "
                             "summary; the last line is the summary, with mu_max_abs_diff")


def policy_config(recording: Recording) -> PolicyConfig:
    """The recorded run's ``[policy]`` overrides (colour order, range, layout, threads), each
    checked as a config file's would be."""
    config = PolicyConfig()
    for key, value in recording.meta.get("config", {}).get("policy", {}).items():
        if key not in ("path", "providers"):
            try:
                set_value(config, "policy", key, value)
            except (UsageError, TypeError, ValueError) as exc:
                raise UsageError(f"{shown(recording.path / 'meta.json')}: config.policy: "
                                 f"{str(exc)[:200]}") from None
    return config


def choose_policy(recording: Recording, path: str | None) -> tuple[Path, str | None]:
    """The policy file and, for the recorded one, the hash it had when it drove."""
    recorded = recording.meta.get("policy", {})
    if path is not None:
        return Path(path), None
    if not recorded.get("path"):
        raise UsageError(f"{recording.path}: no policy recorded; pass --policy FILE.onnx")
    if not Path(recorded["path"]).is_file():
        raise UsageError(f"the recorded policy {recorded['path']} is not there any more; "
                         "pass --policy FILE.onnx")
    return Path(recorded["path"]), recorded.get("sha256")


def replay(recording: Recording, policy: OnnxPolicy, threshold: float,
           emit: Any = None) -> dict[str, Any]:
    """Infer on every recorded frame; ``emit(line)`` gets one per tick. Returns the summary."""
    diffs: list[float] = []
    first_over: int | None = None
    missing = 0
    for record, image in recording.ticks_with_frames():
        if image is None:
            missing += 1
            continue
        mu = policy.infer(image)
        with np.errstate(over="ignore"):  # a recorded mu near the float limit: inf, not noise
            diff = np.abs(mu - np.asarray(record["mu"], dtype=np.float64))
        worst = float(diff.max())
        diffs.append(worst)
        if worst > threshold and first_over is None:
            first_over = int(record["tick"])
        if emit is not None:
            emit(record, mu, worst)
    array = np.asarray(diffs) if diffs else np.zeros(1)
    return {
        "recording": str(recording.path),
        "policy": str(policy.path),
        "ticks": len(recording.ticks),
        "ticks_replayed": len(diffs),
        "ticks_without_frame": missing,
        "mu_max_abs_diff": float(array.max()),
        "mu_p99_abs_diff": float(np.percentile(array, 99)),
        "mu_mean_abs_diff": float(array.mean()),
        "threshold": threshold,
        "ticks_over_threshold": int((array > threshold).sum()),
        "first_tick_over_threshold": first_over,
    }


def run(args: argparse.Namespace) -> int:
    recording = Recording.open(args.recording)
    if not recording.meta:
        raise UsageError(f"{args.recording} is a telemetry file, not a recording: no frames")
    if not args.threshold >= 0:
        raise UsageError(f"--threshold must be >= 0, got {args.threshold:g}")
    path, recorded_sha = choose_policy(recording, args.policy)
    policy = OnnxPolicy.load(path, policy_config(recording))
    size = recording.meta.get("frame_size")
    if size and [policy.spec.width, policy.spec.height] != list(size):
        print(f"jetbot-rt replay: {path} takes {policy.spec.width}x{policy.spec.height}, the "
              f"frames are {size[0]}x{size[1]}: they are resized as the robot would",
              file=sys.stderr)
    sha = sha256_of(path)
    if recorded_sha is not None and sha != recorded_sha:
        print(f"jetbot-rt replay: {path} changed since the recording (sha256 {sha[:12]}, "
              f"recorded {recorded_sha[:12]})", file=sys.stderr)

    def emit(record: dict[str, Any], mu: np.ndarray, worst: float) -> None:
        if args.json:
            print(json.dumps({"tick": record["tick"], "mu_recorded": record["mu"],
                              "mu": [float(m) for m in mu], "abs_diff": worst}))
        elif worst > args.threshold:  # for people: only the ticks that differ that much
            print(f"tick {record['tick']:6d}  recorded [{record['mu'][0]:+.6f} "
                  f"{record['mu'][1]:+.6f}]  replayed [{mu[0]:+.6f} {mu[1]:+.6f}]  "
                  f"|diff| {worst:.2e}")

    summary = replay(recording, policy, args.threshold, emit)
    summary.update(policy_sha256=sha,
                   same_policy=sha == recording.meta.get("policy", {}).get("sha256"))
    if args.json:
        print(json.dumps(summary), flush=True)
        return EXIT_OK
    first = summary["first_tick_over_threshold"]
    print(f"replayed {summary['ticks_replayed']} of {summary['ticks']} ticks "
          f"({summary['ticks_without_frame']} without a frame) with {path}"
          f"{' (the recorded policy)' if summary['same_policy'] else ''}\n"
          f"  |mu - recorded mu|  max {summary['mu_max_abs_diff']:.3g}, "
          f"p99 {summary['mu_p99_abs_diff']:.3g}, mean {summary['mu_mean_abs_diff']:.3g}\n"
          f"  over {args.threshold:g}: {summary['ticks_over_threshold']} ticks"
          + (f", first at tick {first}" if first is not None else ""), flush=True)
    return EXIT_OK
