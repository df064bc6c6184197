"""The non-blocking stream's own promises, one stream on a real pipe: what is dropped when
its reader stalls is exactly what does not fit, and counted; a drain says whether everything
reached the reader; ``unblocked`` gives the streams back after a ``SystemExit`` and says what
a stdout nobody read lost."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from runner import wait_for

from jetbot_rt.service.console import NonBlockingStream

LIVENESS_S = 30.0
"""How long a test waits for something that must happen (never asserted as a duration)."""


def wait_until(predicate: Callable[[], bool]) -> bool:
    return wait_for(predicate, LIVENESS_S, interval=0.001) is not None


def filled_pipe() -> tuple[int, int, int]:
    """A pipe whose buffer is full: its read end, its (blocking) write end, the bytes in it."""
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    filled = 0
    try:
        while True:
            filled += os.write(write_end, b"f" * 4096)
    except BlockingIOError:
        pass
    os.set_blocking(write_end, True)
    return read_end, write_end, filled


@contextmanager
def stream_on_a_pipe(limit: int, full: bool) -> Iterator[tuple[NonBlockingStream, int, int]]:
    """A stream on a pipe's write end (its buffer filled first when ``full``: the writer
    thread blocks on its first line); yields the stream, the read end and the filler's size."""
    read_end, write_end, filled = filled_pipe() if full else (*os.pipe(), 0)
    original = io.TextIOWrapper(io.FileIO(write_end, "w", closefd=False), encoding="utf-8")
    stream = NonBlockingStream(original, limit=limit)
    try:
        yield stream, read_end, filled
    finally:
        stream.close()
        os.set_blocking(read_end, False)
        try:
            while os.read(read_end, 1 << 16):
                pass
        except BlockingIOError:
            pass
        os.close(write_end)
        os.close(read_end)


def read_exactly(fd: int, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = os.read(fd, size - len(data))
        assert chunk, "the pipe ended early"
        data += chunk
    return data


def test_a_stalled_reader_costs_exactly_the_lines_that_do_not_fit_and_they_are_counted() -> None:
    with stream_on_a_pipe(limit=30, full=True) as (stream, read_end, filled):
        stream.write("abc\n")
        # the writer thread has taken the first line and blocks on the full pipe: from here
        # on, what waits for it is exactly what the stream queued after that line
        assert wait_until(lambda: stream._written == 4)
        for _ in range(10):
            stream.write("xyz\n")
        # 7 lines of 4 bytes fit in 30, the other 3 are dropped and counted
        assert stream.lost == 12
        assert read_exactly(read_end, filled) == b"f" * filled
        assert stream.drain(LIVENESS_S)
        assert read_exactly(read_end, 4 + 7 * 4) == b"abc\n" + b"xyz\n" * 7


def test_a_drain_says_everything_reached_a_reader_and_writelines_writes_every_line() -> None:
    with stream_on_a_pipe(limit=1 << 20, full=False) as (stream, read_end, _):
        stream.writelines(["one\n", "two\n", "three"])
        assert stream.drain(LIVENESS_S) is True
        assert read_exactly(read_end, 13) == b"one\ntwo\nthree"
        assert stream.lost == 0


def test_a_drain_says_when_the_reader_had_gone() -> None:
    read_end, write_end = os.pipe()
    os.close(read_end)
    original = io.TextIOWrapper(io.FileIO(write_end, "w", closefd=False), encoding="utf-8")
    stream = NonBlockingStream(original)
    try:
        stream.write("lost\n")
        assert stream.drain(LIVENESS_S) is False
        assert stream.lost == 5 and stream.error
    finally:
        stream.close()
        os.close(write_end)


UNBLOCKED = """
import sys
from jetbot_rt.service import console
try:
    with console.unblocked(drain_s={drain_s}):
        print("x" * 200_000)
        {end}
except SystemExit as exc:
    print("exit", exc.code, type(sys.stdout).__name__, type(sys.stderr).__name__,
          file=sys.stderr)
"""


def test_a_system_exit_gives_the_streams_back() -> None:
    done = subprocess.run([sys.executable, "-c", UNBLOCKED.format(drain_s=5.0,
                                                                  end="sys.exit(4)")],
                          capture_output=True, text=True, timeout=LIVENESS_S)
    assert done.stdout == "x" * 200_000 + "\n"
    assert done.stderr == "exit 4 TextIOWrapper TextIOWrapper\n"


def test_what_a_stdout_nobody_reads_lost_is_said_on_stderr() -> None:
    process = subprocess.Popen([sys.executable, "-c", UNBLOCKED.format(drain_s=0.2, end="")],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # stdout is not read until the process has ended: its pipe fills, the exit cannot wait
        assert wait_until(lambda: process.poll() is not None)
        stderr = process.stderr.read() if process.stderr else ""
    finally:
        process.kill()
        process.communicate()
    assert process.returncode == 0
    (line,) = stderr.splitlines()
    assert line.startswith("jetbot-rt: stdout: ") and line.endswith(
        " bytes not written (nobody read them)"), line


def test_a_stream_sharing_its_writer_still_writes_after_the_other_one_closed() -> None:
    with stream_on_a_pipe(limit=1 << 20, full=False) as (stdout, read_end, _):
        stderr = NonBlockingStream(stdout.original, writer=stdout._writer)  # one file, 2>&1
        stderr.close()
        stdout.write("still here\n")
        assert stdout.drain(LIVENESS_S) is True
        assert read_exactly(read_end, 11) == b"still here\n"


def test_lines_queued_behind_a_write_the_reader_left_are_counted_lost_and_the_fd_closed(
        ) -> None:
    read_end, write_end, _ = filled_pipe()
    original = io.TextIOWrapper(io.FileIO(write_end, "w", closefd=False), encoding="utf-8")
    stream = NonBlockingStream(original)
    try:
        stream.write("abc\n")
        assert wait_until(lambda: stream._written == 4)  # blocked on the full pipe
        stream.write("xyz\n")
        stream.write("xyz\n")
        os.close(read_end)  # the reader goes: the blocked write fails (EPIPE)
        assert stream.drain(LIVENESS_S) is False
        assert stream.lost == 12 and stream.error
        stream.close()
        stream._writer.thread.join(LIVENESS_S)
        assert not stream._writer.thread.is_alive()
        try:
            os.fstat(stream._writer.fd)
        except OSError:
            pass
        else:
            raise AssertionError("the writer's descriptor was left open")
    finally:
        os.close(write_end)


def test_a_descriptor_someone_made_non_blocking_still_gets_every_line() -> None:
    with stream_on_a_pipe(limit=1 << 20, full=True) as (stream, read_end, filled):
        fd = stream.original.fileno()
        os.set_blocking(fd, False)  # the file's status flag: the writer's duplicate shares it
        try:
            stream.write("abc\n")
            assert wait_until(lambda: stream._written == 4)
            time.sleep(0.1)  # lets the writer meet the full pipe (no duration is asserted)
            assert read_exactly(read_end, filled) == b"f" * filled
            assert stream.drain(LIVENESS_S) is True
            os.set_blocking(read_end, False)
            assert os.read(read_end, 100) == b"abc\n"
        finally:
            os.set_blocking(fd, True)
