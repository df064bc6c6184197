"""Output directories of the trainer (a run's ``--out``, the sweep's, ``eval --video``): one
we may fill, opened once, its files named relative to that descriptor. No torch here:
``eval`` imports it.

A directory someone else owns lets them plant a link at any name we are about to write, and
root would write through it; a directory that is itself a link sends every file elsewhere. So
neither is used: one line, exit 2. Root's directories are fine for anyone (root could write
anywhere anyway).
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import stat
from pathlib import Path

from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import shown
from jetbot_rt.errors import UsageError


def inside(fd: int, name: str = "") -> Path:
    """The path of ``name`` in the directory open as ``fd``: Linux resolves
    ``/proc/self/fd/N`` to that directory whatever has been renamed since."""
    return Path(f"/proc/self/fd/{fd}", name)


def own_directory(path: str | Path, what: str = "output directory",
                  parent: int | None = None, display: Path | None = None) -> int:
    """A descriptor of the directory ``path`` (a name inside ``parent`` when given), created
    if missing, that we may fill: not a symbolic link, owned by us or by root. Else
    ``UsageError``, one line (``display``: the path it names)."""
    display = Path(path) if display is None else display
    if parent is None:
        safe_file.no_link_of_others_above(path, f"cannot write to {what}")
    try:
        if parent is None:
            Path(path).mkdir(parents=True, exist_ok=True)
        else:
            with contextlib.suppress(FileExistsError):
                os.mkdir(path, dir_fd=parent)
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC,
                     dir_fd=parent)
    except OSError as exc:
        try:
            link = stat.S_ISLNK(os.stat(path, dir_fd=parent, follow_symlinks=False).st_mode)
        except OSError:
            link = False
        reason = ("a symbolic link (not followed: name the directory itself)" if link
                  else "not a directory" if exc.errno in (errno.EEXIST, errno.ENOTDIR)
                  else exc.strerror or str(exc))
        raise UsageError(f"cannot write to {what} {shown(display)}: {reason}") from None
    owner, me = os.fstat(fd).st_uid, os.geteuid()
    if owner not in (me, 0):
        os.close(fd)
        raise UsageError(f"{what} {shown(display)} is owned by uid {owner}, not by you (uid {me})"
                         " or root: its owner could plant links where files are written; use "
                         "a directory of your own")
    return fd


def writable_directory(path: str | Path) -> int:
    """``own_directory(path)``, checked writable before any work that would be lost (a file
    created and removed); its descriptor, which the caller closes."""
    fd = own_directory(path)
    probe = f".write_test.{secrets.token_hex(6)}"
    try:
        os.close(safe_file.create_new(inside(fd, probe)))
        os.unlink(probe, dir_fd=fd)
    except OSError as exc:
        os.close(fd)
        raise UsageError(f"cannot write to output directory {shown(path)}: "
                         f"{exc.strerror or exc}") from None
    return fd
