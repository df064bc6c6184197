"""The one way to read a file we did not just write ourselves, and to write an output beside one.

A config, a recording someone copied or planted, a policy's metadata: any of them may be a
FIFO that blocks ``open`` for ever, a link to ``/dev/zero`` that never ends, gigabytes, bytes
that are not text, JSON with ``Infinity`` or 50,000 nested brackets. Every reader here

- opens without blocking (``O_NONBLOCK``: a FIFO without a writer opens at once) and, where the
  caller says so, without following a final symbolic link (``O_NOFOLLOW``, for files *inside*
  a directory somebody else may write to);
- reads only a regular file (``fstat`` after the open, so a rename between a check and the open
  cannot swap one in), at most ``limit`` bytes (a file larger, or growing past it, is refused);
- decodes UTF-8 strictly (a byte-order mark is accepted), and parses JSON strictly: no
  ``NaN``/``Infinity``, no integer longer than 30 digits (Python 3.8 converts a long one in
  quadratic time), no lone surrogate escape (it cannot be printed), nesting caught;

and says what is wrong as one ``UsageError`` naming the file. Outputs written next to untrusted
data (``report``'s ``run.png`` beside a recording) go through ``replaced_file``: a new file
created with ``O_CREAT|O_EXCL|O_NOFOLLOW`` under a random name, renamed over the target only
once complete, so a planted link at the target is replaced, never followed.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import secrets
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Union

from jetbot_rt.errors import UsageError

PathLike = Union[str, "os.PathLike[str]"]
KIB = 1024
MIB = 1024 * KIB
MAX_INT_DIGITS = 30
"""Longer integer literals are refused: nothing we read needs more than 2**64, and CPython
before 3.11 has no limit on ``int(str)``, whose time grows with the square of the length."""


def shown(path: PathLike) -> str:
    """A path as messages show it: a byte that is not UTF-8 as ``\\xNN``, never a lone
    surrogate that a strict stream cannot print."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def text_path(path: PathLike, what: str) -> str:
    """``path`` as text, or ``UsageError`` when its bytes are not UTF-8: OpenCV crashes on
    such a name (SIGSEGV, seen in ``replay``) and matplotlib raises, so none reaches them."""
    try:
        return os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        raise UsageError(f"{what} {shown(path)}: the path is not valid UTF-8 text "
                         "(rename it)") from None


def size_text(limit: int) -> str:
    return f"{limit // MIB} MiB" if limit % MIB == 0 else f"{limit // KIB} KiB"


def open_regular(path: PathLike, what: str, *, follow_links: bool = True) -> int:
    """A descriptor of ``path`` opened for reading, which is a regular file; else
    ``UsageError``. Never blocks (FIFO, device); ``follow_links=False`` refuses a final link."""
    flags = (os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC
             | (0 if follow_links else os.O_NOFOLLOW))
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        if exc.errno == errno.ELOOP and not follow_links:
            raise UsageError(f"cannot read {what} {shown(path)}: a symbolic link "
                             "(not followed here)") from None
        raise UsageError(f"cannot read {what} {shown(path)}: {exc.strerror or exc}") from None
    try:
        mode = os.fstat(fd).st_mode
    except OSError as exc:  # pragma: no cover - fstat of an open descriptor
        os.close(fd)
        raise UsageError(f"cannot read {what} {shown(path)}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        os.close(fd)
        kind = "a directory" if stat.S_ISDIR(mode) else "not a regular file"
        raise UsageError(f"cannot read {what} {shown(path)}: {kind}")
    os.set_blocking(fd, True)  # a regular file: reads do not wait on anyone
    return fd


def _too_large(path: PathLike, what: str, limit: int) -> UsageError:
    return UsageError(f"{what} {shown(path)} is larger than {size_text(limit)}")


def read_bytes(path: PathLike, what: str, limit: int, *, follow_links: bool = True) -> bytes:
    """The whole file, at most ``limit`` bytes (a larger one is refused, however it reports
    its size: ``/proc`` files say 0)."""
    fd = open_regular(path, what, follow_links=follow_links)
    try:
        if os.fstat(fd).st_size > limit:
            raise _too_large(path, what, limit)
        chunks = []
        size = 0
        while size <= limit:
            chunk = os.read(fd, min(MIB, limit + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise UsageError(f"cannot read {what} {shown(path)}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if size > limit:
        raise _too_large(path, what, limit)
    return b"".join(chunks)


def decode(data: bytes, path: PathLike, what: str) -> str:
    """Strict UTF-8; the error names the first bad byte and its line."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise UsageError(f"{what} {shown(path)} is not UTF-8: byte 0x{data[exc.start]:02x} "
                         f"at line {line}") from None
    return text[1:] if text.startswith("\ufeff") else text


def read_text(path: PathLike, what: str, limit: int, *, follow_links: bool = True) -> str:
    return decode(read_bytes(path, what, limit, follow_links=follow_links), path, what)


def iter_lines(path: PathLike, what: str, limit: int, line_limit: int, *,
               follow_links: bool = True) -> Iterator[tuple[int, bytes, bool]]:
    """``(line number, bytes without the newline, complete)`` for each line; only the last
    can be incomplete (no newline: a write cut short). A line longer than ``line_limit`` or a
    file longer than ``limit`` is refused; memory stays within one line."""
    fd = open_regular(path, what, follow_links=follow_links)
    try:
        if os.fstat(fd).st_size > limit:
            raise _too_large(path, what, limit)
        with os.fdopen(os.dup(fd), "rb") as stream:
            total = 0
            number = 0
            while True:
                line = stream.readline(line_limit + 2)
                if not line:
                    return
                number += 1
                total += len(line)
                if total > limit:
                    raise _too_large(path, what, limit)
                complete = line.endswith(b"\n")
                body = line[:-1] if complete else line
                if len(body) > line_limit:
                    raise UsageError(f"{what} {shown(path)} line {number}: longer than "
                                     f"{size_text(line_limit)}")
                yield number, body, complete
    except OSError as exc:
        raise UsageError(f"cannot read {what} {shown(path)}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number (JSON has no NaN or Infinity)")


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise ValueError(f"an integer of {len(text)} digits")
    return int(text)


_DECODER = json.JSONDecoder(parse_constant=_no_constant, parse_int=_bounded_int)


def _printable(value: Any) -> None:
    """Every string (and key) encodes as UTF-8: a ``\\udcff`` escape decodes to a lone
    surrogate that ``print`` would raise on."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, str):
            item.encode("utf-8")
        elif isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)


def loads(text: str) -> Any:
    """Strict JSON (see the module's docstring); ``ValueError`` says why not."""
    try:
        value = _DECODER.decode(text)
        if "\\u" in text:
            _printable(value)
    except RecursionError:
        raise ValueError("nested too deeply") from None
    except UnicodeEncodeError:
        raise ValueError("a string holds a lone surrogate escape (\\udXXX)") from None
    return value


def read_json(path: PathLike, what: str, limit: int, *, follow_links: bool = True) -> Any:
    text = read_text(path, what, limit, follow_links=follow_links)
    try:
        return loads(text)
    except ValueError as exc:
        raise UsageError(f"{what} {shown(path)} is not valid JSON: {exc}") from None


def no_link_of_others_above(path: PathLike, what: str) -> None:
    """``UsageError`` if a directory above ``path`` is a symbolic link that neither this user
    nor root owns: its owner chose where it leads, so where a directory we create below it
    would be. A missing directory ends the walk (what is below is created by us)."""
    for above in reversed(Path(os.path.abspath(path)).parents):
        try:
            info = os.lstat(above)
        except OSError:
            return
        if stat.S_ISLNK(info.st_mode) and info.st_uid not in (os.geteuid(), 0):
            raise UsageError(f"{what} {shown(path)}: {shown(above)} is a symbolic link of uid "
                             f"{info.st_uid} (refused: it could lead anywhere)")


def create_new(path: PathLike, mode: int = 0o666, *, dir_fd: int | None = None) -> int:
    """A descriptor (read and write) of a file created now at ``path`` (relative to the
    directory ``dir_fd`` if given): never an existing file, never through a link planted
    there (``O_CREAT|O_EXCL|O_NOFOLLOW``). ``OSError`` (``FileExistsError`` for anything
    already at ``path``)."""
    return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                   mode, dir_fd=dir_fd)


@contextlib.contextmanager
def replaced_file(directory: PathLike, name: str, mode: int = 0o666) -> Iterator[int]:
    """A new file for ``directory/name``, written through the descriptor yielded, that
    replaces ``name`` only when the block ends without an exception (else it is removed).

    It is created under a random name with ``O_EXCL|O_NOFOLLOW`` relative to the directory
    opened once, and renamed over ``name``: a symbolic or hard link planted at ``name`` is
    replaced, not written through, and a reader never sees half a file. ``OSError`` escapes.
    """
    dir_fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        temp = f".{name}.{secrets.token_hex(6)}.part"
        fd = os.open(temp, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                     mode, dir_fd=dir_fd)
        try:
            yield fd
            os.replace(temp, name, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(temp, dir_fd=dir_fd)
            raise
        finally:
            os.close(fd)
    finally:
        os.close(dir_fd)


@contextlib.contextmanager
def path_for_library(fd: int, suffix: str) -> Iterator[str]:
    """A path that leads to the open file ``fd`` and ends in ``suffix``, for a library that
    takes only a file name and picks the container by its extension (OpenCV's video writer).

    A symbolic link to ``/proc/self/fd/N`` in a fresh private directory (mode 0700): whatever
    happens to the file's own directory meanwhile, the library opens our file."""
    private = Path(tempfile.mkdtemp(prefix="jetbot-rt-"))
    link = private / f"out{suffix}"
    try:
        os.symlink(f"/proc/self/fd/{fd}", link)
        yield str(link)
    finally:
        with contextlib.suppress(OSError):
            link.unlink()
        with contextlib.suppress(OSError):
            private.rmdir()
