"""Reading a recording (docs/RECORDING.md) or a bare telemetry file, for replay and report.

A recording cut short (the process killed, the disk full) is read as far as it goes: a
half-written last line is skipped, and ticks whose frame never reached the file have none.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jetbot_rt.errors import UsageError
from jetbot_rt.recorder import FORMAT, VERSION


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """Records of a JSON Lines file; an unparsable line (a cut-off last one) is skipped."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise UsageError(f"cannot read {path}: {exc.strerror or exc}") from None
    records = []
    for line in lines:
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if isinstance(record, dict):
            records.append(record)
    return records


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
        return [r for r in self.records if "event" not in r and "tick" in r]

    @property
    def events(self) -> list[dict[str, Any]]:
        return [r for r in self.records if "event" in r]

    @classmethod
    def open(cls, path: str | Path) -> Recording:
        path = Path(path)
        if path.is_file():
            records = read_jsonl(path)
            if not records:
                raise UsageError(f"{path}: no JSON Lines records in it")
            return cls(path, records)
        meta_path = path / "meta.json"
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise UsageError(f"{path} is not a recording (no readable meta.json: "
                             f"{getattr(exc, 'strerror', None) or exc})") from None
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise UsageError(f"{path}: recording format {meta.get('format')!r} version "
                             f"{meta.get('version')!r}; this jetbot-rt reads {FORMAT!r} "
                             f"version {VERSION}")
        summary: dict[str, Any] = {}
        if (path / "summary.json").is_file():
            try:
                summary = json.loads((path / "summary.json").read_text(encoding="utf-8"))
            except (OSError, ValueError):
                summary = {}
        return cls(path, read_jsonl(path / "ticks.jsonl"), meta, summary,
                   path / meta.get("frames", "frames.mkv"))

    def frames(self) -> Iterator[np.ndarray]:
        """The recorded frames in order, HxWx3 uint8 RGB, as the policy received them."""
        if self.frames_path is None or not self.frames_path.is_file():
            return
        capture = cv2.VideoCapture(str(self.frames_path))
        try:
            while True:
                ok, image = capture.read()
                if not ok:
                    return
                yield np.ascontiguousarray(image[:, :, ::-1])
        finally:
            capture.release()

    def ticks_with_frames(self) -> Iterator[tuple[dict[str, Any], np.ndarray | None]]:
        """Each tick record with its frame (None when it was dropped or never written)."""
        frames = self.frames()
        next_index = 0
        for record in self.ticks:
            index = record.get("frame")
            image: np.ndarray | None = None
            while index is not None and next_index <= index:
                image = next(frames, None)
                next_index = next_index + 1 if image is not None else index + 1
            yield record, image
