"""The token a monitor on a non-loopback address requires: read from ``[monitor] token_file``
when it exists and nobody else may read it, else generated and written there with mode 0600."""

from __future__ import annotations

import hmac
import os
import secrets
import stat
import string

from jetbot_rt.config import safe_file
from jetbot_rt.errors import UsageError

MIN_TOKEN_CHARS = 16
MAX_TOKEN_BYTES = 1024
TOKEN_CHARS = frozenset(string.ascii_letters + string.digits + "-._~")
"""What may appear in a URL's query and a cookie without escaping."""


def generate() -> str:
    return secrets.token_urlsafe(32)


def read_token(path: str) -> str:
    """The token in ``path``, or ``UsageError``: a file others may read or write (or not ours,
    or a link) would let someone else stop the robot or read the page."""
    fd = safe_file.open_regular(path, "[monitor] token_file", follow_links=False)
    try:  # checked and read through one descriptor: what was checked is what is read
        info = os.fstat(fd)
        data = os.read(fd, MAX_TOKEN_BYTES + 1)
    finally:
        os.close(fd)
    if info.st_mode & 0o077:
        raise UsageError(f"[monitor] token_file {safe_file.shown(path)} has mode "
                         f"{stat.S_IMODE(info.st_mode):04o}: others may read it "
                         f"(chmod 600 {safe_file.shown(path)})")
    if info.st_uid != os.geteuid():
        raise UsageError(f"[monitor] token_file {safe_file.shown(path)} belongs to uid "
                         f"{info.st_uid}, not to this user")
    if len(data) > MAX_TOKEN_BYTES:
        raise UsageError(f"[monitor] token_file {safe_file.shown(path)} is larger than "
                         f"{MAX_TOKEN_BYTES} bytes")
    text = safe_file.decode(data, path, "[monitor] token_file").strip()
    if len(text) < MIN_TOKEN_CHARS or not set(text) <= TOKEN_CHARS:
        raise UsageError(f"[monitor] token_file {safe_file.shown(path)}: the token must be at "
                         f"least {MIN_TOKEN_CHARS} characters of A-Z a-z 0-9 - . _ ~")
    return text


def write_token(path: str, token: str) -> None:
    """A new file, mode 0600 (never an existing file, never through a link)."""
    try:
        fd = safe_file.create_new(path, 0o600)
    except OSError as exc:
        raise UsageError(f"[monitor] token_file {safe_file.shown(path)}: cannot create it: "
                         f"{exc.strerror or exc}") from None
    try:
        os.fchmod(fd, 0o600)  # whatever the umask
        os.write(fd, (token + "\n").encode())
    finally:
        os.close(fd)


def load_or_create(path: str | None) -> tuple[str, bool]:
    """The token and whether it is new (then the caller prints it once)."""
    if path is not None and os.path.lexists(path):
        return read_token(path), False
    token = generate()
    if path is not None:
        write_token(path, token)
    return token, True


def matches(given: str | None, token: str) -> bool:
    """Constant time in the token's content (``hmac.compare_digest``)."""
    if given is None:
        return False
    return hmac.compare_digest(given.encode(errors="replace"), token.encode())
