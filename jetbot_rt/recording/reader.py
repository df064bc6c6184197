"""Reading a recording (docs/RECORDING.md) or a bare telemetry file, for replay and report.

Nothing in a recording is trusted: it may have been copied from a robot, downloaded, or planted
in a shared directory. Each file is read through ``safe_file`` (a regular file, not through a
symbolic link, size-capped, strict UTF-8 and JSON) and every record is validated once, here,
before anything uses it: types, finite numbers within bounds, tick times and numbers that only
go forward, frame indices that only go forward and never past their tick. Whatever is wrong is
one ``UsageError`` naming the file, the line and the key.

A record keeps only the keys replay and report read, each checked, with a text cut to
``MAX_TEXT`` characters: unknown keys (a line's worth of ``{}`` is 20 times its size in Python
objects) never stay in memory. The records held are counted (``RecordChecker.held``, each
record's size) and more than ``RECORDS_BYTES`` of them is refused: a file within its
cap, however it is written, costs at most that plus one line being parsed.

A recording cut short (the process killed, the disk full) is read as far as it goes: a
half-written last line (no newline) is skipped, and ticks whose frame never reached the video
have none.
"""

from __future__ import annotations

import math
import os
import stat
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import MIB, shown
from jetbot_rt.errors import UsageError
from jetbot_rt.recording.recorder import FORMAT, VERSION
from jetbot_rt.runtime.policy import MAX_INPUT_SIDE

META_BYTES = 4 * MIB
"""``meta.json`` and ``summary.json``: a few KB (the config, the policy's metadata)."""
TICKS_BYTES = 128 * MIB
"""``ticks.jsonl`` or a telemetry file: about 230 bytes a tick, so some 5 hours at 30 Hz."""
LINE_BYTES = 1 * MIB
"""One record; the longest we write (the ``end`` event with the run's summary) is a few KB.
Parsing one costs at most ~25 MiB for the moment it takes (1 MiB of ``{},``)."""
RECORDS_BYTES = 512 * MIB
"""The records held in memory (``RecordChecker.held``): a recording of ours at ``TICKS_BYTES``
holds ~400 MiB; a Jetson Nano has 4 GB."""
MAX_TEXT = 1000
"""Characters kept of a record's text (a state, an event's name or reason)."""
SHARED_TEXTS = 1000
"""Distinct short texts (states, event names) held once and shared by the records."""
MAX_TIME_S = 1e9
"""``t``: 30 years of run time; a larger one is not a time a run had."""
MAX_MS = 1e9
MAX_COUNT = 2**53
"""Tick numbers, frame indices, counters: integers a float can still hold exactly."""
RATE_HZ = (0.1, 1000.0)
READABLE = tuple(range(1, VERSION + 1))
"""Format versions this reader takes: 2 added the drive's tick keys (``driver``, ``human``,
``policy_mu``), which a version 1 recording simply lacks."""


class Invalid(Exception):
    """A value that breaks the format; the message says which key and why."""


def _number(record: dict[str, Any], key: str, low: float, high: float,
            optional: bool = False) -> float | None:
    value = record.get(key)
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Invalid(f"{key} must be a number, got {_kind(value)}")
    if not (math.isfinite(value) and low <= value <= high):
        raise Invalid(f"{key} must be within [{low:g}, {high:g}], got {value!r}")
    return value


def _integer(record: dict[str, Any], key: str, low: int, high: int = MAX_COUNT,
             optional: bool = False) -> int | None:
    value = record.get(key)
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int):
        raise Invalid(f"{key} must be an integer, got {_kind(value)}")
    if not low <= value <= high:
        raise Invalid(f"{key} must be within [{low}, {high}], got {value}")
    return value


def _pair(record: dict[str, Any], key: str, bound: float, optional: bool = False) -> None:
    value = record.get(key)
    if value is None and optional:
        return
    if not isinstance(value, list) or len(value) != 2:
        raise Invalid(f"{key} must be a list of two numbers, got {_kind(value)}")
    for index in range(2):
        _number({f"{key}[{index}]": value[index]}, f"{key}[{index}]", -bound, bound)


def _text(record: dict[str, Any], key: str, optional: bool = True) -> str | None:
    value = record.get(key)
    if not (isinstance(value, str) or (value is None and optional)):
        raise Invalid(f"{key} must be text, got {_kind(value)}")
    return value


def _table(record: dict[str, Any], key: str) -> dict[str, Any]:
    value = record.get(key, {})
    if not isinstance(value, dict):
        raise Invalid(f"{key} must be an object, got {_kind(value)}")
    return value


def _kind(value: Any) -> str:
    if value is None:
        return "nothing"
    text = repr(value)
    return f"{type(value).__name__} {text[:40]}{'...' if len(text) > 40 else ''}"


def check_meta(meta: Any) -> dict[str, Any]:
    """``meta.json``'s keys that jetbot_rt uses; the message of ``Invalid`` names the key."""
    if not isinstance(meta, dict):
        raise Invalid(f"must be a JSON object, got {_kind(meta)}")
    version = meta.get("version")
    if meta.get("format") != FORMAT or isinstance(version, bool) or version not in READABLE:
        raise Invalid(f"recording format {str(meta.get('format'))[:40]!r} version "
                      f"{str(version)[:10]!r}; this jetbot-rt reads {FORMAT!r} "
                      f"versions {', '.join(map(str, READABLE))}")
    size = meta.get("frame_size")
    if not isinstance(size, list) or len(size) != 2:
        raise Invalid(f"frame_size must be [width, height], got {_kind(size)}")
    _integer({"frame_size[0]": size[0]}, "frame_size[0]", 1, MAX_INPUT_SIDE)
    _integer({"frame_size[1]": size[1]}, "frame_size[1]", 1, MAX_INPUT_SIDE)
    _number(meta, "rate_hz", *RATE_HZ)
    frames = meta.get("frames")
    if not isinstance(frames, str) or frames in ("", ".", "..") or "/" in frames \
            or "\0" in frames:
        raise Invalid(f"frames must be a file name in the recording, got {_kind(frames)}")
    _number(meta, "max_speed", 1e-9, 1.0, optional=True)
    for key in ("backend", "source", "codec"):
        _text(meta, key)
    policy = _table(meta, "policy")
    for key in ("path", "sha256"):
        _text(policy, f"{key}", optional=True)
    if not isinstance(policy.get("metadata", {}), dict):
        raise Invalid("policy.metadata must be an object")
    config = _table(meta, "config")
    if not isinstance(config.get("policy", {}), dict):
        raise Invalid(f"config.policy must be an object, got {_kind(config.get('policy'))}")
    return meta


def check_summary(summary: Any) -> dict[str, Any]:
    if not isinstance(summary, dict):
        raise Invalid(f"must be a JSON object, got {_kind(summary)}")
    for key in ("frames_written", "frames_dropped", "records_written", "records_lost"):
        _integer(summary, key, 0, optional=True)
    _text(summary, "error")
    _table(summary, "run")
    return summary


TICK_KEYS = ("t", "tick", "state", "mu", "cmd", "frame_age_ms", "infer_ms", "tick_ms",
             "overruns", "pose", "goal", "driver", "human", "policy_mu", "frame")
"""``pose`` (x, y of the sim's [x, y, yaw]) and ``goal`` (sim only) for the report's map;
``driver`` (``jetbot-rt drive``: human or policy) for its takeovers; ``human`` (the person's
command in force, or null) and ``policy_mu`` (where a policy ran) for ``jetbot-train
finetune`` (format version 2)."""
MAX_POSITION_M = 1e6
EVENT_KEYS = ("t", "event", "reason", "fault", "success", "cmd")


def _record_bound() -> int:
    """Bytes a kept record can hold besides its texts, at most: a dict of every tick key, two
    lists of two floats, a large number per key, its slot in the list."""
    number = max(sys.getsizeof(2.0**60), sys.getsizeof(2**60))
    pair = sys.getsizeof([0.5, 0.5]) + 2 * number
    return (sys.getsizeof(dict.fromkeys(TICK_KEYS)) + 6 * pair + len(TICK_KEYS) * number
            + sys.getsizeof([None]))


RECORD_BYTES = _record_bound()
TEXT_BYTES = sys.getsizeof("\U0001f600" * MAX_TEXT)
"""A kept text at most (``MAX_TEXT`` characters of 4 bytes)."""


class RecordChecker:
    """Checks records in file order and returns each as a new dict of the keys replay and
    report read. Tick records: ``t`` and ``tick`` only go forward (events come from other
    threads and are not ordered); ``frame`` indices only go forward and never past the
    number of ticks before them (a tick writes at most one frame). ``held``: the bytes the
    records returned so far hold, counted with ``sys.getsizeof`` (at most ``RECORD_BYTES``
    each, plus their texts' ``TEXT_BYTES``; texts shared are counted once)."""

    def __init__(self, with_frames: bool) -> None:
        self.with_frames = with_frames
        self.ticks = 0
        self.last_t = -math.inf
        self.last_tick = -1
        self.last_frame = -1
        self.held = 0
        self._texts: dict[str, str] = {}

    def _kept_text(self, value: str | None) -> str | None:
        """``value`` cut to ``MAX_TEXT``; a short one shared with the records before."""
        if value is None:
            return None
        if len(value) > MAX_TEXT:
            value = value[:MAX_TEXT - 3] + "..."
        shared = self._texts.get(value)
        if shared is not None:
            return shared
        self.held += sys.getsizeof(value)
        if len(value) <= 40 and len(self._texts) < SHARED_TEXTS:
            self._texts[value] = value
        return value

    def check(self, record: Any) -> dict[str, Any]:
        kept = self._checked(record)
        held = sys.getsizeof(kept) + 8  # and its slot in the list of records
        for key, value in list(kept.items()):
            if key in ("state", "event", "reason", "driver"):
                kept[key] = self._kept_text(value)  # counts itself, unless shared
            elif isinstance(value, list):
                held += sys.getsizeof(value) + sys.getsizeof(value[0]) + sys.getsizeof(value[1])
            else:
                held += sys.getsizeof(value)
        self.held += held
        return kept

    def _checked(self, record: Any) -> dict[str, Any]:
        if not isinstance(record, dict):
            raise Invalid(f"a record must be a JSON object, got {_kind(record)}")
        if "event" in record:
            _text(record, "event", optional=False)
            _number(record, "t", 0.0, MAX_TIME_S)
            _text(record, "reason")
            for key in ("fault", "success"):  # success: an evaluated episode's end
                if not isinstance(record.get(key, False), bool):
                    raise Invalid(f"{key} must be true or false, got {_kind(record.get(key))}")
            _pair(record, "cmd", 1.0, optional=True)
            return _kept(record, EVENT_KEYS)
        if "tick" not in record:
            raise Invalid("neither a tick record (no tick) nor an event (no event)")
        t = _number(record, "t", 0.0, MAX_TIME_S)
        tick = _integer(record, "tick", 0)
        assert t is not None and tick is not None
        if t < self.last_t:
            raise Invalid(f"t goes back: {t!r} after {self.last_t!r}")
        if tick <= self.last_tick:
            raise Invalid(f"tick {tick} after tick {self.last_tick}")
        _pair(record, "mu", math.inf)
        _pair(record, "cmd", 1.0)
        for key in ("frame_age_ms", "infer_ms", "tick_ms"):
            _number(record, key, -MAX_MS, MAX_MS)
        _integer(record, "overruns", 0)
        _text(record, "state")
        _text(record, "driver")
        pose = record.get("pose")
        if pose is not None:
            if not isinstance(pose, list) or len(pose) not in (2, 3):
                raise Invalid(f"pose must be a list of 2 or 3 numbers, got {_kind(pose)}")
            for index, value in enumerate(pose):
                _number({f"pose[{index}]": value}, f"pose[{index}]", -MAX_POSITION_M,
                        MAX_POSITION_M)
        _pair(record, "goal", MAX_POSITION_M, optional=True)
        _pair(record, "human", 1.0, optional=True)
        _pair(record, "policy_mu", math.inf, optional=True)
        if self.with_frames:
            frame = _integer(record, "frame", 0, self.ticks, optional=True)
            if frame is not None:
                if frame <= self.last_frame:
                    raise Invalid(f"frame {frame} after frame {self.last_frame}")
                self.last_frame = frame
        self.last_t, self.last_tick = t, tick
        self.ticks += 1
        return _kept(record, TICK_KEYS if self.with_frames else TICK_KEYS[:-1])


def _kept(record: dict[str, Any], keys: tuple[str, ...]) -> dict[str, Any]:
    """A new dict of ``keys`` that ``record`` has (checked: numbers, bools, None, texts or
    lists of two numbers, copied so that nothing else of the parsed line stays alive)."""
    kept = {}
    for key in keys:
        if key in record:
            value = record[key]
            kept[key] = [float(value[0]), float(value[1])] if isinstance(value, list) else value
    return kept


def read_records(path: Path, with_frames: bool) -> list[dict[str, Any]]:
    """Every record of a JSON Lines file, each checked; a cut-off last line is skipped.
    ``with_frames``: a recording's ``ticks.jsonl`` (not followed through a link), else a
    telemetry file the user named."""
    checker = RecordChecker(with_frames)
    records = []
    for number, line, complete in safe_file.iter_lines(
            path, "recording file" if with_frames else "telemetry file", TICKS_BYTES,
            LINE_BYTES, follow_links=not with_frames):
        if not line.strip():
            continue
        try:
            record = safe_file.loads(line.decode("utf-8"))
        except ValueError as exc:  # UnicodeDecodeError included
            if not complete:
                break  # the write was cut short: the record never finished
            reason = (f"not UTF-8: byte 0x{line[exc.start]:02x}"
                      if isinstance(exc, UnicodeDecodeError) else str(exc))
            raise UsageError(f"{shown(path)} line {number}: not a JSON record "
                             f"({reason})") from None
        try:
            records.append(checker.check(record))
        except Invalid as exc:
            raise UsageError(f"{shown(path)} line {number}: {exc}") from None
        if checker.held > RECORDS_BYTES:
            raise UsageError(f"{shown(path)} line {number}: more records than "
                             f"{RECORDS_BYTES // MIB} MiB of memory holds (a recording of "
                             f"ours of {TICKS_BYTES // MIB} MiB needs ~400)")
    return records


def _read_object(path: Path, check: Any) -> dict[str, Any]:
    data = safe_file.read_json(path, "recording file", META_BYTES, follow_links=False)
    try:
        return check(data)  # type: ignore[no-any-return]
    except Invalid as exc:
        raise UsageError(f"{shown(path)}: {exc}") from None


@dataclass
class Recording:
    """``meta`` is empty and ``frames_path`` None for a bare telemetry file."""

    path: Path
    records: list[dict[str, Any]]
    meta: dict[str, Any] = field(default_factory=dict)
    summary: dict[str, Any] = field(default_factory=dict)
    frames_path: Path | None = None

    @property
    def ticks(self) -> list[dict[str, Any]]:
        return [r for r in self.records if "event" not in r]

    @property
    def events(self) -> list[dict[str, Any]]:
        return [r for r in self.records if "event" in r]

    @classmethod
    def open(cls, path: str | Path) -> Recording:
        safe_file.text_path(path, "recording")
        path = Path(path)
        try:
            is_dir = stat.S_ISDIR(os.stat(path).st_mode)
        except OSError as exc:
            raise UsageError(f"cannot read {shown(path)}: {exc.strerror or exc}") from None
        if not is_dir:
            records = read_records(path, with_frames=False)
            if not records:
                raise UsageError(f"{shown(path)}: no JSON Lines records in it")
            return cls(path, records)
        if not os.path.lexists(path / "meta.json"):
            raise UsageError(f"{shown(path)} is not a recording (no meta.json)")
        meta = _read_object(path / "meta.json", check_meta)
        summary: dict[str, Any] = {}
        if os.path.lexists(path / "summary.json"):  # written at the end: a cut run has none
            summary = _read_object(path / "summary.json", check_summary)
        return cls(path, read_records(path / "ticks.jsonl", with_frames=True), meta, summary,
                   path / meta["frames"])

    def frames(self) -> Iterator[np.ndarray]:
        """The recorded frames in order, HxWx3 uint8 RGB, as the policy received them. The
        video must hold frames of ``meta.json``'s ``frame_size``; OpenCV is given the open
        file (``/proc/self/fd/N``), never a name somebody could swap."""
        if self.frames_path is None or not os.path.lexists(self.frames_path):
            return
        fd = safe_file.open_regular(self.frames_path, "recording file", follow_links=False)
        capture = cv2.VideoCapture(f"/proc/self/fd/{fd}")
        try:
            if not capture.isOpened():
                return
            width, height = self.meta["frame_size"]
            found = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)),
                     int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            if found != (width, height):
                raise UsageError(f"{shown(self.frames_path)} holds {found[0]}x{found[1]} "
                                 f"frames, meta.json says {width}x{height}")
            while True:
                ok, image = capture.read()
                if not ok:
                    return
                if image.shape != (height, width, 3):
                    raise UsageError(f"{shown(self.frames_path)}: a frame of shape "
                                     f"{image.shape}, expected {height}x{width}x3")
                yield np.ascontiguousarray(image[:, :, ::-1])
        finally:
            capture.release()
            os.close(fd)

    def ticks_with_frames(self) -> Iterator[tuple[dict[str, Any], np.ndarray | None]]:
        """Each tick record with its frame (None when it was dropped or never written). Frame
        indices only go forward (checked on reading), so each frame is decoded at most once
        and the video is read no further than the last tick needs."""
        frames = self.frames()
        next_index = 0
        exhausted = False
        try:
            for record in self.ticks:
                index = record.get("frame")
                image: np.ndarray | None = None
                while index is not None and next_index <= index and not exhausted:
                    image = next(frames, None)
                    exhausted = image is None
                    next_index += 1
                yield record, image
        finally:
            frames.close()
