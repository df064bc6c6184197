"""JSON Lines telemetry: one record per tick, plus event records carrying an ``event`` key.

A telemetry file that can no longer be written (disk full, directory removed) does not stop
the robot: telemetry is for people, the safety chain does not depend on it. The writer reports
the failure once on stderr, stops writing and keeps the count of lost records for the summary.
A removed file (its directory deleted) raises no write error on Linux, the records would go to
an unlinked inode; the writer checks the link count before each record and treats that the same.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

from jetbot_rt.errors import UsageError


class Telemetry:
    def __init__(self, path: str | Path | None) -> None:
        self.path = Path(path) if path else None
        self._file: IO[str] | None = None
        self._lock = threading.Lock()
        self.t0 = time.monotonic()
        self.error: str | None = None
        self.lost = 0
        if self.path is not None:
            try:
                self._file = open(self.path, "w", encoding="utf-8", buffering=1)  # noqa: SIM115
            except OSError as exc:
                raise UsageError(
                    f"cannot write telemetry {self.path}: {exc.strerror or exc}"
                ) from None

    @property
    def enabled(self) -> bool:
        return self._file is not None

    def _write(self, record: dict[str, Any]) -> None:
        if self._file is None:
            return
        with self._lock:
            if self.error is not None:
                self.lost += 1
                return
            try:
                if os.fstat(self._file.fileno()).st_nlink == 0:
                    raise FileNotFoundError("file removed while running")
                self._file.write(json.dumps(record, separators=(",", ":")) + "\n")
            except (OSError, ValueError) as exc:
                self.error = str(getattr(exc, "strerror", None) or exc)
                self.lost += 1
                print(f"jetbot-rt: telemetry {self.path} not writable any more "
                      f"({self.error}); still driving, records dropped", file=sys.stderr)

    def record(self, record: dict[str, Any]) -> None:
        self._write(record)

    def event(self, name: str, **fields: Any) -> dict[str, Any]:
        record = {"t": round(time.monotonic() - self.t0, 6), "event": name, **fields}
        self._write(record)
        return record

    def close(self) -> None:
        with self._lock:
            if self._file is not None:
                with contextlib.suppress(OSError):
                    self._file.close()
                self._file = None
