"""Where a runtime keeps its files, and which of them ``jetbot-rt`` trusts.

The runtime directory holds each runtime's control socket (``control-<pid>.sock``,
``stop_socket.py``) and the record of the board the last runtime drove (``board.json``,
written by ``hal/ownership.py`` when it takes the board), which ``jetbot-rt stop`` (systemd's
``ExecStopPost``) reads when its config cannot be read.

Which directory: ``$JETBOT_RT_RUNTIME_DIR``, else ``$RUNTIME_DIRECTORY`` (systemd's; the first
of several), else ``$XDG_RUNTIME_DIR/jetbot-rt``. Without any of them (sudo, a root login,
cron), root uses ``/run/jetbot-rt`` and every other user ``/tmp/jetbot-rt-<uid>``. Root never
uses ``/tmp``: anyone can create a name there first, while only root can create one in
``/run``; and ``/run/jetbot-rt`` is the service's own ``RuntimeDirectory``, so a
``sudo jetbot-rt stop`` finds the service's socket and its board record.

A second local user is an adversary. A directory is used only if, seen without following a
link, it is a directory, owned by the caller or root, and writable by nobody else; root also
trusts ``/run/jetbot-rt`` whoever owns it (systemd gives it to the service's user) while
``/run`` is root's alone. In a trusted directory a socket or a record is used only if it is
what it says (a socket, a regular file; never a link) and owned by the caller, root or the
directory's owner. Anything else is ignored, and ``stop`` names it.

A runtime whose ``/tmp/jetbot-rt-<uid>`` is held by another user is neither refused nor
intercepted: it uses a private directory of its own, ``/tmp/jetbot-rt-<uid>.XXXXXX`` (made by
``mkdtemp``: mode 0700, a name nobody can take first), the first such directory of this user
that already exists, else a new one; ``stop`` looks there too. A directory named in the
environment that is not the caller's is a refusal (exit 2): the user chose it.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import stat
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from jetbot_rt.config.safe_file import loads, open_regular, replaced_file, shown
from jetbot_rt.errors import UsageError

SERVICE_DIR = Path("/run/jetbot-rt")
TMP = Path("/tmp")
RECORD_NAME = "board.json"
MAX_RECORD_BYTES = 4096
MAX_ENTRIES = 256
"""Entries looked at per directory (and ``/tmp/jetbot-rt-<uid>.*`` directories): a directory
stuffed with names costs ``stop`` at most this many ``lstat`` calls."""
_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
_RECORD_KEYS = {"i2c_bus", "address", "emulator", "pid"}


def printable(path: Path) -> str:
    """A path as one line may show it: another user picks the names in ``/tmp``, and a newline
    or a terminal's escape sequence in one must not reach the screen as such."""
    return "".join(c if c.isprintable() else f"\\x{ord(c):02x}" if ord(c) < 256
                   else f"\\u{ord(c):04x}" for c in shown(path))


def configured_dir() -> Path | None:
    """The directory the environment names, if any."""
    explicit = os.environ.get("JETBOT_RT_RUNTIME_DIR")
    if explicit:
        return Path(explicit)
    systemd = os.environ.get("RUNTIME_DIRECTORY")
    if systemd:
        return Path(systemd.split(":")[0])  # systemd joins several with ':'
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg:
        return Path(xdg) / "jetbot-rt"
    return None


def fallback_dir() -> Path:
    """Without a directory in the environment: root's ``/run/jetbot-rt``, else
    ``/tmp/jetbot-rt-<uid>``."""
    uid = os.getuid()
    return SERVICE_DIR if uid == 0 else TMP / f"jetbot-rt-{uid}"


def default_dir() -> Path:
    return configured_dir() or fallback_dir()


MAX_TMP_ENTRIES = 100_000
"""Names of ``/tmp`` looked at for ``/tmp/jetbot-rt-<uid>.*``: another user filling ``/tmp``
costs a search at most this many (a few tens of milliseconds)."""


def _tmp_alternatives() -> Iterator[Path]:
    """``/tmp/jetbot-rt-<uid>.*``, at most ``MAX_ENTRIES`` of them, by name."""
    prefix = f"jetbot-rt-{os.getuid()}."
    names = []
    with contextlib.suppress(OSError), os.scandir(TMP) as entries:
        for count, entry in enumerate(entries):
            if count >= MAX_TMP_ENTRIES:
                break
            if entry.name.startswith(prefix):
                names.append(entry.name)
                if len(names) >= MAX_ENTRIES:
                    break
    return (TMP / name for name in sorted(names))


def _service_dir_is_roots(path: Path) -> bool:
    """For root: ``/run/jetbot-rt`` counts as root's whoever owns it, while ``/run`` is
    root's alone (then only root, systemd, can have put it there)."""
    if os.geteuid() != 0 or path != SERVICE_DIR:
        return False
    try:
        parent = os.lstat(path.parent)
    except OSError:
        return False
    return stat.S_ISDIR(parent.st_mode) and parent.st_uid == 0 and not parent.st_mode & 0o022


def _why_untrusted(path: Path, st: os.stat_result) -> str | None:
    """None when ``path`` (its ``lstat``) is a directory we may trust, else why not."""
    if stat.S_ISLNK(st.st_mode):
        return "a symbolic link"
    if not stat.S_ISDIR(st.st_mode):
        return "not a directory"
    if st.st_uid not in (os.geteuid(), 0) and not _service_dir_is_roots(path):
        return f"owned by uid {st.st_uid}"
    if st.st_mode & 0o022:
        return f"writable by others (mode {stat.S_IMODE(st.st_mode):04o})"
    return None


# ---- the runtime's side: its own directory ------------------------------------------------

_resolved: dict[Path, Path] = {}


def _make_private(path: Path) -> str | None:
    """Create ``path`` (0700) if missing; None when it is ours to use, else why not.
    Raises ``OSError`` when it cannot be created."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with contextlib.suppress(FileExistsError):
        os.mkdir(path, 0o700)
    try:
        fd = os.open(path, _DIR_FLAGS)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.ENOTDIR):
            return "a symbolic link" if os.path.islink(path) else "not a directory"
        raise
    try:
        st = os.fstat(fd)
        if st.st_uid != os.geteuid():
            if not _service_dir_is_roots(path):
                return f"owned by uid {st.st_uid}"
            return f"writable by others (mode {stat.S_IMODE(st.st_mode):04o})" \
                if st.st_mode & 0o022 else None
        if stat.S_IMODE(st.st_mode) != 0o700:
            os.fchmod(fd, 0o700)  # ours: nobody else may list or write it
    finally:
        os.close(fd)
    return None


def private_dir(path: Path | None = None) -> Path:
    """This process's runtime directory (``path``, default ``default_dir()``), created 0700
    if missing and checked without following links. The ``/tmp`` fallback held by another
    user gives way to a private ``/tmp/jetbot-rt-<uid>.XXXXXX``; any other directory that is
    not ours is a ``UsageError``."""
    wanted = Path(path) if path is not None else default_dir()
    known = _resolved.get(wanted)
    if known is not None and _make_private(known) is None:
        return known
    problem = _make_private(wanted)
    if problem is None:
        chosen = wanted
    elif wanted == TMP / f"jetbot-rt-{os.getuid()}":
        chosen = _private_alternative()
    else:
        raise UsageError(f"runtime directory {wanted} is {problem}, not this user's own "
                         "(mode 0700): set JETBOT_RT_RUNTIME_DIR to a directory of yours")
    _resolved[wanted] = chosen
    return chosen


def _private_alternative() -> Path:
    for candidate in _tmp_alternatives():
        with contextlib.suppress(OSError):
            st = os.lstat(candidate)
            if stat.S_ISDIR(st.st_mode) and st.st_uid == os.geteuid() \
                    and _make_private(candidate) is None:
                return candidate
    return Path(tempfile.mkdtemp(prefix=f"jetbot-rt-{os.getuid()}.", dir=TMP))


def write_board_record(i2c_bus: int, address: int, emulator: str | None) -> Path | None:
    """Record the board this process drives in its runtime directory, for a ``stop`` whose
    config cannot be read. Best effort: a directory that cannot be used records nothing (the
    run does not depend on it). Written to a new file, then renamed over the old one."""
    record = {"i2c_bus": i2c_bus, "address": address, "pid": os.getpid(),
              "emulator": os.path.abspath(emulator) if emulator else None}
    try:
        directory = private_dir()
        with replaced_file(directory, RECORD_NAME, 0o644) as fd:
            os.write(fd, json.dumps(record).encode())
    except (OSError, UsageError):
        return None
    return directory / RECORD_NAME


# ---- stop's side: what it may trust ----------------------------------------------------


@dataclass
class Found:
    """What ``search()`` found in the runtime directories."""

    sockets: list[Path] = field(default_factory=list)
    records: list[tuple[Path, int]] = field(default_factory=list)
    """Record files and the uid of their directory's owner, most relevant first."""
    ignored: list[str] = field(default_factory=list)
    """``path (why)`` of every directory or entry not trusted."""
    problems: list[str] = field(default_factory=list)
    """Trusted directories that could not be read."""


def search_dirs(alternatives: bool = True) -> list[Path]:
    """Where ``stop`` looks: the directory the environment names (and, for
    ``$XDG_RUNTIME_DIR``, the service's); else the fallback (a non-root user's private
    alternatives in ``/tmp`` too, unless ``alternatives`` is False) and the service's."""
    configured = configured_dir()
    if configured is not None:
        explicit = os.environ.get("JETBOT_RT_RUNTIME_DIR") or os.environ.get(
            "RUNTIME_DIRECTORY")
        return [configured] if explicit else [configured, SERVICE_DIR]
    fallback = fallback_dir()
    if fallback == SERVICE_DIR:
        return [SERVICE_DIR]
    return [fallback, *(_tmp_alternatives() if alternatives else ()), SERVICE_DIR]


_KINDS = {stat.S_IFSOCK: "not a socket", stat.S_IFREG: "not a regular file"}


def _trusted_entry(entry: os.DirEntry, want: int, owners: tuple[int, ...]) -> str | None:
    """None when the entry is of type ``want`` (``stat.S_IFSOCK``, ``S_IFREG``), not a link,
    and owned by one of ``owners``; else why not."""
    st = entry.stat(follow_symlinks=False)
    if stat.S_ISLNK(st.st_mode):
        return "a symbolic link"
    if stat.S_IFMT(st.st_mode) != want:
        return _KINDS[want]
    if st.st_uid not in owners:
        return f"owned by uid {st.st_uid}"
    return None


def search(socket_glob: str | None = None, max_sockets: int = 0) -> Found:
    """The trusted sockets matching ``socket_glob`` (at most ``max_sockets``, the rest
    ignored) in ``search_dirs()``, and board records; what was not trusted is named. Without
    a glob (the board record only, read before the stop is written) not in ``/tmp``'s
    alternatives: how full another user makes ``/tmp`` cannot delay the stop."""
    import fnmatch

    found = Found()
    for directory in search_dirs(alternatives=socket_glob is not None):
        try:
            st = os.lstat(directory)
        except FileNotFoundError:
            continue
        except OSError as exc:
            found.problems.append(f"{printable(directory)}: {exc.strerror or exc}")
            continue
        why = _why_untrusted(directory, st)
        if why is not None:
            found.ignored.append(f"{printable(directory)} ({why})")
            continue
        owners = (os.geteuid(), 0, st.st_uid)
        try:
            with os.scandir(directory) as entries:
                for count, entry in enumerate(entries):
                    if count >= MAX_ENTRIES:
                        found.ignored.append(
                            f"{printable(directory)} (more than {MAX_ENTRIES} entries)")
                        break
                    path = directory / entry.name
                    if entry.name == RECORD_NAME:
                        why = _trusted_entry(entry, stat.S_IFREG, owners)
                        if why is None:
                            found.records.append((path, st.st_uid))
                        else:
                            found.ignored.append(f"{printable(path)} ({why})")
                    elif socket_glob and fnmatch.fnmatch(entry.name, socket_glob):
                        why = _trusted_entry(entry, stat.S_IFSOCK, owners)
                        if why is None and len(found.sockets) >= max_sockets:
                            why = f"more than {max_sockets} sockets"
                        if why is None:
                            found.sockets.append(path)
                        else:
                            found.ignored.append(f"{printable(path)} ({why})")
        except OSError as exc:  # the service's directory, seen by another user
            found.problems.append(f"{printable(directory)}: {exc.strerror or exc}")
    found.sockets.sort()
    return found


@dataclass(frozen=True)
class BoardRecord:
    i2c_bus: int
    address: int
    emulator: str | None
    path: Path


def _read_record(path: Path, owners: tuple[int, ...]) -> BoardRecord:
    """One record, read as untrusted: not through a link, a regular file of one of
    ``owners``, at most ``MAX_RECORD_BYTES``, JSON of the known keys, each validated as the
    config validates ``[motors]``. Raises ``UsageError`` saying what is wrong."""
    from jetbot_rt.config.schema import set_value
    from jetbot_rt.config.sections import MotorsConfig

    fd = open_regular(path, "board record", follow_links=False)
    try:
        if os.fstat(fd).st_uid not in owners:
            raise UsageError("not this user's or root's")
        data = os.read(fd, MAX_RECORD_BYTES + 1)
    except OSError as exc:
        raise UsageError(exc.strerror or str(exc)) from None
    finally:
        os.close(fd)
    if len(data) > MAX_RECORD_BYTES:
        raise UsageError(f"larger than {MAX_RECORD_BYTES} bytes")
    try:
        record = loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise UsageError(f"not JSON: {exc}") from None
    if not isinstance(record, dict) or not {"i2c_bus", "address"} <= set(record) \
            or not set(record) <= _RECORD_KEYS:
        raise UsageError(f"not a board record (keys: {', '.join(sorted(_RECORD_KEYS))})")
    if type(record.get("pid", 0)) is not int:
        raise UsageError("pid must be an integer")
    motors = MotorsConfig()
    for key in ("i2c_bus", "address", "emulator"):
        try:  # the checks of [motors], the same ranges and types
            set_value(motors, "motors", key, record.get(key))
        except UsageError as exc:
            raise UsageError(str(exc).replace("[motors] ", "", 1)) from None
    emulator = motors.emulator
    if emulator is not None:
        try:
            usable = os.path.isabs(emulator) and stat.S_ISREG(os.lstat(emulator).st_mode)
        except (OSError, ValueError):  # ValueError: a NUL in the name
            usable = False
        if not usable:
            raise UsageError(f"emulator {emulator!r} is not an absolute path to a regular "
                             "file (any more)")
    return BoardRecord(motors.i2c_bus, motors.address, emulator, path)


def read_board_record() -> tuple[BoardRecord | None, str | None]:
    """The first valid board record in ``search_dirs()``, or None and why none."""
    found = search()
    whys = [entry for entry in found.ignored if f"/{RECORD_NAME} (" in entry]
    for path, dir_owner in found.records:
        try:
            return _read_record(path, (os.geteuid(), 0, dir_owner)), None
        except UsageError as exc:
            whys.append(f"{printable(path)}: {exc}")
    return None, "; ".join(whys) or "no board record in the runtime directory"
