"""A second local user, made up by the test: a numeric uid with no passwd entry.

The interpreter may live where another uid cannot read it (here: under /root, mode 0700), so a
child started as that uid could not even exec Python. Instead the child starts as root, imports
what it needs, then drops to the uid (``setgroups``, ``setgid``, ``setuid``) before it runs the
test's code: every system call the code makes is that user's, which is the point. Needs root;
``needs_root`` skips with the reason otherwise.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import random
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

needs_root = pytest.mark.skipif(
    os.geteuid() != 0, reason="acting as a second local user needs root (setuid to a new uid)")

_PRELUDE = """
import os, sys
_uid = int(sys.argv[1])
import locale, gettext, json, fnmatch, selectors, tempfile, struct, errno, signal  # noqa: E401
for _name in sys.argv[2].split(","):
    if _name:
        __import__(_name)
os.setgroups([])
os.setgid(_uid)
os.setuid(_uid)
sys.argv = ["-c", *sys.argv[3:]]
"""


def unused_uid() -> int:
    """A uid nobody has: no passwd entry, no /tmp/jetbot-rt-<uid> (tests beside this one
    under pytest-xdist pick others)."""
    while True:
        uid = random.randrange(40_000, 60_000)
        try:
            pwd.getpwuid(uid)
        except KeyError:
            if not any(Path("/tmp").glob(f"jetbot-rt-{uid}*")):
                return uid


def as_user(uid: int, code: str, *args: str, modules: tuple[str, ...] = (),
            env: dict | None = None, timeout: float = 30.0, **popen: object
            ) -> subprocess.CompletedProcess[str]:
    """Run ``code`` (``sys.argv[1:]`` = ``args``) as ``uid``, ``modules`` imported first;
    in ``env``, else in ``user_env()``."""
    return subprocess.run(command(uid, code, *args, modules=modules), capture_output=True,
                          text=True, timeout=timeout, cwd="/",
                          env=user_env() if env is None else dict(env, HOME="/"), **popen)


def _robot_side_modules() -> tuple[str, ...]:
    """Every module of the robot side. The second uid may not be able to read the checkout
    (a clone in a 0700 directory): whatever the code under test imports lazily later must be
    imported before the drop."""
    package = Path(__file__).resolve().parent.parent / "jetbot_rt"
    names = []
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        if parts[1] in ("sim", "train", "tasks", "calibration") or parts[-1] in (
                "__main__", "calibrate", "report", "replay"):
            continue
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return tuple(names)


ROBOT_SIDE_MODULES = _robot_side_modules()


def command(uid: int, code: str, *args: str, modules: tuple[str, ...] = ()) -> list[str]:
    if any(name.startswith("jetbot_rt") for name in modules):
        modules = (*modules, *ROBOT_SIDE_MODULES)
    return [sys.executable, "-c", _PRELUDE + code, str(uid), ",".join(modules), *args]


def user_env() -> dict:
    """No runtime directory in the environment (sudo, cron): the fallbacks are under test."""
    names = ("JETBOT_RT_RUNTIME_DIR", "RUNTIME_DIRECTORY", "XDG_RUNTIME_DIR")
    return dict({k: v for k, v in os.environ.items() if k not in names}, HOME="/")


@contextlib.contextmanager
def tmp_names(uid: int) -> Iterator[None]:
    """Removes ``/tmp/jetbot-rt-<uid>`` and ``/tmp/jetbot-rt-<uid>.*`` afterwards."""
    try:
        yield
    finally:
        for path in Path("/tmp").glob(f"jetbot-rt-{uid}*"):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink()


def shared_dir(owner: int) -> Path:
    """A fresh directory under /tmp that ``owner`` owns (the tests' own are root's 0700)."""
    import tempfile

    path = Path(tempfile.mkdtemp(prefix="jetbot-rt-test-", dir="/tmp"))
    os.chown(path, owner, owner)
    return path
