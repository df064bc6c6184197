"""PyBullet's C code prints to file descriptors 1 and 2 directly: a GUI client's start and end
are some 50 lines (threads, the GL context, the example browser's shut-down) around the few a
user should read. ``pybullet_chatter_filtered`` sends both descriptors to a temporary file
for the duration of a call and passes on only the lines that report a problem."""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys
import tempfile
from collections.abc import Iterator

PROBLEM = re.compile(r"error|fail|cannot|can't|unable|warning|not found|invalid",
                     re.IGNORECASE)
"""A line PyBullet prints that a person should see (its own ``b3Warning``/``b3Error`` lines
say so in these words; the chatter never does)."""


@contextlib.contextmanager
def pybullet_chatter_filtered() -> Iterator[list[str]]:
    """Yields a list that holds, after the block, every line the block printed from C;
    those matching ``PROBLEM`` are also written to stderr (``pybullet: ...``). What Python
    prints meanwhile (ours, a warning) still goes where it went: ``sys.stdout`` and
    ``sys.stderr`` write to the original descriptors for the block."""
    streams = (sys.stdout, sys.stderr)
    captured: list[str] = []
    saved = []
    for fd in (1, 2):
        with contextlib.suppress(OSError):
            saved.append(os.dup(fd))
    if len(saved) < 2 or None in streams:
        # a closed descriptor or stream (`>&-`): nothing to keep clean; never open one
        for fd in saved:
            os.close(fd)
        yield captured
        return
    for stream in streams:
        stream.flush()
    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            sys.stdout, sys.stderr = (
                io.TextIOWrapper(io.FileIO(fd, "w", closefd=False), line_buffering=True,
                                 encoding=getattr(stream, "encoding", None),
                                 errors=getattr(stream, "errors", None))
                for fd, stream in zip(saved, streams, strict=True))
            try:
                yield captured
            finally:
                for stream in (sys.stdout, sys.stderr):
                    stream.flush()
                sys.stdout, sys.stderr = streams
                os.dup2(saved[0], 1)
                os.dup2(saved[1], 2)
                sink.seek(0)
                text = sink.read(1 << 20).decode("utf-8", errors="replace")
                captured.extend(line for line in text.splitlines() if line.strip())
                for line in captured:
                    if PROBLEM.search(line):
                        print(f"pybullet: {line.strip()}", file=sys.stderr, flush=True)
    finally:
        for fd in saved:
            os.close(fd)
