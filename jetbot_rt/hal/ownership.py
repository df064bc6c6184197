"""One owner per motor bus: an advisory ``flock`` on the bus's device node.

Every process that may write a non-zero duty to a board takes an exclusive ``flock`` on
``/dev/i2c-N`` (with the emulator: on ``<state file>.owner``) before it writes anything, and
holds it until it exits; the kernel drops it when the process dies, SIGKILL included. The lock
is on the device node itself, so it does not depend on the environment, the user or a runtime
directory: anyone who can open the bus to write it can open it to lock it, and two processes
that start at the same moment cannot both get it. ``jetbot-rt stop`` takes no lock (it always
writes the stop); it reads the owner's pid from ``/proc/locks`` to say who drives.

Taking the board also records it (bus, address, emulator state file) in the runtime directory
(``runtime_dir.write_board_record``): systemd's ``ExecStopPost`` finds the board the runtime
drove even when the config it is given cannot be read. The record outlives the process on
purpose (``ExecStopPost`` runs after it); systemd removes the service's directory after that.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import stat
from pathlib import Path

from jetbot_rt.errors import UsageError
from jetbot_rt.service.runtime_dir import write_board_record

_held: dict[str, BoardLock] = {}


def bus_device(bus_number: int, emulator: str | None = None) -> Path:
    """What the owner locks: the bus's device node, or the emulator's ``.owner`` file."""
    if emulator:
        return Path(emulator + ".owner")
    return Path(f"/dev/i2c-{bus_number}")


def _open(path: Path) -> int:
    flags = os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK | os.O_NOCTTY
    if not path.name.endswith(".owner"):
        return os.open(path, flags)
    return _open_emulator_lock(path, flags | os.O_NOFOLLOW)


def _open_emulator_lock(path: Path, flags: int) -> int:
    """``<state file>.owner``: whoever can open it can take the lock, so it grants what the
    state file grants and no more: its owner, its mode (``rw`` bits of user and group, never
    others'). Never through a link (root would create the file a link names), and no
    ``O_CREAT`` on an existing file (``protected_regular`` refuses that to root in /tmp when
    another user owns it). An existing one must be a regular file of this user, root or the
    state file's owner; one open to others is closed to them where this user may change it
    (one only root may change is used as it is: its owner is trusted, the risk a refused run).
    OSError: cannot open; UsageError: refused, saying why."""
    state = path.with_name(path.name[: -len(".owner")])
    try:
        state_st: os.stat_result | None = os.stat(state, follow_symlinks=False)
    except OSError:
        state_st = None
    if state_st is not None and not stat.S_ISREG(state_st.st_mode):
        state_st = None  # a link's owner is nobody to trust (the emulator refuses it anyway)
    trusted = {os.geteuid(), 0} | ({state_st.st_uid} if state_st else set())
    wanted = (stat.S_IMODE(state_st.st_mode) if state_st else 0o666 & ~_umask()) & 0o660
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        try:
            fd = os.open(path, flags | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:  # another process created it just now
            fd = os.open(path, flags)
        else:
            _give_like(fd, path, state_st, wanted)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise UsageError(f"{path} is a symbolic link (refused: the emulator's owner lock "
                             "must be a file of its own; remove the link)") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_uid not in trusted:
            what = "not a regular file" if not stat.S_ISREG(st.st_mode) else \
                f"owned by uid {st.st_uid}, not by this user, root or the state file's owner"
            raise UsageError(f"{path} is {what} (refused: whoever can open it can take the "
                             "board's owner lock; remove it)")
        if st.st_mode & 0o007:
            with contextlib.suppress(OSError):  # not ours to change: root's next run will
                _give_like(fd, path, state_st, wanted)
    except BaseException:
        os.close(fd)
        raise
    return fd


def _umask() -> int:
    """The process's umask, read without changing it (``os.umask`` would, for every thread)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    return 0o022


def _give_like(fd: int, path: Path, state_st: os.stat_result | None, mode: int) -> None:
    """A lock file created now: the state file's owner and mode; with no state file yet, the
    emulator's rule (a root process gives it to its directory's owner)."""
    os.fchmod(fd, mode)
    if os.geteuid() != 0:
        return
    owner = state_st
    if owner is None:
        with contextlib.suppress(OSError):
            parent = os.stat(path.parent)
            owner = parent if parent.st_uid != 0 else None
    if owner is not None and owner.st_uid != 0:
        with contextlib.suppress(OSError):
            os.fchown(fd, owner.st_uid, owner.st_gid)


def owner_pids(path: Path) -> list[int]:
    """Pids holding a ``flock`` on ``path``, from ``/proc/locks`` (empty if none or unknown)."""
    try:
        st = os.stat(path, follow_symlinks=False)
        locks = Path("/proc/locks").read_text()
    except OSError:
        return []
    key = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    pids = []
    for line in locks.splitlines():
        fields = line.split()
        # "1: FLOCK  ADVISORY  WRITE 1234 fe:00:56 0 EOF"; waiters carry "->" and are not owners
        if len(fields) >= 6 and fields[1] == "FLOCK" and fields[5] == key:
            pid = int(fields[4])
            if pid > 0:
                pids.append(pid)
    return pids


def owned(path: Path) -> bool:
    """Whether some process holds the owner lock: a shared ``flock`` attempt that fails.
    Authoritative where ``/proc/locks`` cannot name the holder (another pid namespace)."""
    try:
        fd = _open(path)
    except (OSError, UsageError):
        return False  # no such bus, or a lock file no runtime of ours would take
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as exc:
        return exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN)
    finally:
        os.close(fd)  # drops the shared lock if it was granted
    return False


def describe(pids: list[int]) -> str:
    """``pid 1234 (jetbot-rt run --backend real)``, or ``another process``."""
    if not pids:
        return "another process (its pid is not visible here)"
    pid = pids[0]
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(
            errors="replace").strip()
    except OSError:
        cmd = ""
    words = cmd.split()
    if len(words) > 1 and "jetbot-rt" in words[1]:
        words = words[1:]  # "python .../jetbot-rt run ..." reads as "jetbot-rt run ..."
    shown = " ".join([Path(words[0]).name, *words[1:4]]) if words else ""
    return f"pid {pid}" + (f" ({shown})" if shown else "")


class BoardLock:
    """The exclusive ``flock`` on one bus; ``release()`` or the process's end frees it."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self._fd: int | None = fd
        self._users = 1

    @classmethod
    def acquire(cls, bus_number: int, emulator: str | None = None,
                address: int | None = None) -> BoardLock:
        """Own bus ``bus_number`` (or the emulator in the file ``emulator``) or raise
        ``UsageError`` naming the owner. Re-entrant within a process (``check --spin`` owns
        the bus before it opens the drive). With ``address``, the board is recorded in the
        runtime directory once owned."""
        path = bus_device(bus_number, emulator)
        held = _held.get(str(path))
        if held is not None and held._fd is not None:
            held._users += 1
            if address is not None:
                write_board_record(bus_number, address, emulator)
            return held
        try:
            fd = _open(path)
        except OSError as exc:
            raise UsageError(
                f"cannot open {path}: {exc.strerror or exc} "
                "(is the bus enabled and is this user in the i2c group?)"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise UsageError(f"cannot lock {path}: {exc.strerror or exc}") from None
            raise UsageError(
                f"the motor board on I2C bus {bus_number} is driven by "
                f"{describe(owner_pids(path))}; stop it first (jetbot-rt stop)"
            ) from None
        lock = cls(path, fd)
        _held[str(path)] = lock
        if address is not None:
            write_board_record(bus_number, address, emulator)
        return lock

    def release(self) -> None:
        self._users -= 1
        if self._users > 0 or self._fd is None:
            return
        os.close(self._fd)  # closing the only descriptor drops the flock
        self._fd = None
        _held.pop(str(self.path), None)
