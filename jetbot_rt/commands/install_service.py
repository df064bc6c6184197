"""``jetbot-rt install-service``: write the systemd unit and, if absent, a default config.

Everything is checked before anything is written, so an error (exit 2, one line) leaves the
target tree as it was. ``--root`` installs into a staging tree (an SD-card image, a test):
every path it reads or writes stays inside that tree (no ``..``, no symbolic link that leads
out). Every value that goes into the unit is refused when systemd could read it as something
else (a control character, text that is not UTF-8, a user name systemd would not take) and
escaped as systemd.syntax(7) says otherwise (quotes, ``%%``, ``$$``).
"""

from __future__ import annotations

import argparse
import grp
import os
import pkgutil
import pwd
import re
import shlex
import shutil
import sys
import sysconfig
import unicodedata
from pathlib import Path, PurePosixPath

from jetbot_rt.config import safe_file
from jetbot_rt.errors import UsageError

UNIT_NAME = "jetbot-rt.service"
UNIT_DIR = PurePosixPath("/etc/systemd/system")
DEFAULT_CONFIG = "/etc/jetbot-rt/config.toml"
DEFAULT_USER = "jetbot"
CREATE_USER_HINT = "sudo useradd --system --groups i2c,video jetbot"
SUPPLEMENTARY_GROUPS = ("i2c", "video")
# ProtectHome=yes hides these; an installation living there needs ProtectHome=read-only.
HOME_DIRS = (PurePosixPath("/home"), PurePosixPath("/root"), PurePosixPath("/run/user"))
PLACEHOLDERS = ("@EXECUTABLE@", "@USER@", "@CONFIG@", "@PROTECT_HOME@")
# A name useradd and systemd both take (systemd's own rule is looser, useradd's stricter on
# the first character); anything else is refused rather than escaped: User= expands
# specifiers and takes no quotes.
USER_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,31}")
# Characters systemd would read as something else inside a unit file line: every C0/C1
# control (a newline starts a new line, so a new setting), and the Unicode line separators.
REFUSED_CATEGORIES = ("Cc", "Zl", "Zp")
LOCAL_FAMILIES = "RestrictAddressFamilies=AF_UNIX AF_NETLINK"
NETWORK_FAMILIES = "AF_INET AF_INET6"
"""What the unit adds when the config serves the monitor ([monitor] listen)."""
FILE_LIMIT = 1 << 20
"""The largest unit or passwd file read back (both are a few KiB)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--root", default="/", metavar="DIR",
        help="install into this tree instead of / (a staging directory); default /",
    )
    parser.add_argument(
        "--user", default=DEFAULT_USER, metavar="NAME",
        help=f"the unprivileged user the service runs as (default {DEFAULT_USER}; create it "
        f"with: {CREATE_USER_HINT})",
    )
    parser.add_argument(
        "--config", default=DEFAULT_CONFIG, metavar="PATH",
        help=f"config file the service reads, as seen on the target (default {DEFAULT_CONFIG}); "
        "a commented default is written there unless the file exists",
    )
    parser.add_argument(
        "--force", action="store_true",
        help="replace an existing unit file (an existing config is never replaced)",
    )


def run(args: argparse.Namespace) -> int:
    root = Path(safe_file.text_path(args.root, "--root"))
    if not root.is_dir():
        raise UsageError(f"--root {args.root}: not a directory")
    config = target_path(args.config)
    check_user(args.user, root)
    executable = find_executable()

    unit_path = staged(root, UNIT_DIR / UNIT_NAME)
    config_path = staged(root, config)
    monitor = None
    if config_path.exists() or config_path.is_symlink():
        from jetbot_rt.config.sections import load_config

        # an existing config is kept: it must be one the service reads
        monitor = load_config(config_path).monitor.listen
    unit_text = render_unit(executable, args.user, config, network=monitor is not None)
    unit_action = "wrote"
    if unit_path.exists() or unit_path.is_symlink():
        if read_text(unit_path, "the unit") == unit_text:
            unit_action = "unchanged"
        elif not args.force:
            raise UsageError(f"{unit_path} exists and differs; pass --force to replace it")
        else:
            unit_action = "replaced"
    if unit_action != "unchanged":
        write_file(unit_path, unit_text)
    config_action = "kept existing"
    if not config_path.exists():
        write_file(config_path, default_config_text())
        config_action = "wrote default"

    print(f"{unit_action} {unit_path}")
    print(f"{config_action} {config_path}")
    if monitor is not None:
        print(f"note: [monitor] listen = {monitor!r} in the config, so the unit allows IP "
              f"sockets ({NETWORK_FAMILIES}); without it, only local ones")
    if protect_home(executable, config) != "yes":
        print("note: this installation lives under /home or /root, so the unit uses "
              "ProtectHome=read-only; a venv in /opt/jetbot-rt keeps home directories hidden")
    print_next_steps(root, args.user, config, executable)
    return 0


def target_path(value: str) -> PurePosixPath:
    """``--config`` as a path on the target: absolute, naming a file, no ``..`` (which would
    lead out of ``--root`` here and somewhere unexpected there)."""
    text = unit_value("--config", value)
    config = PurePosixPath(text)
    if not config.is_absolute():
        raise UsageError(f"--config {value}: must be an absolute path on the target")
    if ".." in config.parts:
        raise UsageError(f"--config {value}: must not contain '..'")
    if config.name in ("", ".") or text.endswith("/"):
        raise UsageError(f"--config {value}: must name a file")
    return config


def check_user(name: str, root: Path) -> None:
    """The user must exist on the target: the host's user database, or the staged
    ``etc/passwd`` when installing into another tree that has one."""
    if USER_NAME.fullmatch(name) is None:
        raise UsageError(f"--user {name!r}: not a user name a systemd unit can take "
                         "(letters, digits, '_', '.', '-'; at most 32)")
    passwd = staged(root, PurePosixPath("/etc/passwd"))
    if root.resolve() != Path("/") and passwd.is_file():
        names = {line.split(":", 1)[0] for line in read_text(passwd, "passwd").splitlines()}
        exists = name in names
    else:
        try:
            pwd.getpwnam(name)
            exists = True
        except KeyError:
            exists = False
    if not exists:
        raise UsageError(
            f"user {name!r} does not exist; create it with: {CREATE_USER_HINT} "
            f"(or pass --user NAME)"
        )
    if root.resolve() == Path("/"):
        for group in SUPPLEMENTARY_GROUPS:
            try:
                grp.getgrnam(group)
            except KeyError:
                print(f"warning: group {group!r} does not exist here; the unit's "
                      f"SupplementaryGroups= will fail to start until it does", file=sys.stderr)


def find_executable() -> Path:
    """This installation's ``jetbot-rt`` script: the one running now, else the one next to
    this Python, else the first on PATH."""
    candidates = []
    if Path(sys.argv[0]).name == "jetbot-rt":
        candidates.append(Path(sys.argv[0]))
    candidates.append(Path(sysconfig.get_path("scripts")) / "jetbot-rt")
    on_path = shutil.which("jetbot-rt")
    if on_path:
        candidates.append(Path(on_path))
    for candidate in candidates:
        if candidate.is_file() and os.access(candidate, os.X_OK):
            # abspath, not resolve(): a venv's script path must stay inside the venv.
            return Path(os.path.abspath(candidate))
    raise UsageError("cannot find this installation's jetbot-rt executable; reinstall with pip")


def protect_home(executable: Path, config: PurePosixPath) -> str:
    """``yes`` unless the program or its config lives in a home directory."""
    paths = [PurePosixPath(executable), config, PurePosixPath(Path(__file__).resolve())]
    interpreter = shebang_interpreter(executable)
    if interpreter is not None:
        paths.append(interpreter)
    in_home = any(home == path or home in path.parents for path in paths for home in HOME_DIRS)
    return "read-only" if in_home else "yes"


def shebang_interpreter(executable: Path) -> PurePosixPath | None:
    try:
        with executable.open("rb") as script:
            first = script.readline(512)
    except OSError:
        return None
    if not first.startswith(b"#!"):
        return None
    words = first[2:].decode(errors="replace").split()
    return PurePosixPath(words[0]) if words else None


def render_unit(executable: Path, user: str, config: PurePosixPath, *,
                network: bool = False) -> str:
    """The unit: the template with its placeholders filled in its settings, never in its
    comments (which name the placeholders to say what the template is). ``network``: the
    config serves the monitor, so ``RestrictAddressFamilies`` also allows IP sockets."""
    if USER_NAME.fullmatch(user) is None:
        raise UsageError(f"--user {user!r}: not a user name a systemd unit can take")
    values = {
        "@EXECUTABLE@": systemd_word(unit_value("the jetbot-rt executable's path",
                                                os.fsdecode(executable)), program=True),
        "@USER@": user,
        "@CONFIG@": systemd_word(unit_value("--config", str(config))),
        "@PROTECT_HOME@": protect_home(executable, config),
    }
    lines = []
    for line in unit_template().splitlines(keepends=True):
        if not line.lstrip().startswith(("#", ";")):
            for placeholder, value in values.items():
                line = line.replace(placeholder, value)
        lines.append(line)
    text = "".join(lines)
    if network:
        assert LOCAL_FAMILIES in text, "the unit template's RestrictAddressFamilies changed"
        text = text.replace(LOCAL_FAMILIES, f"{LOCAL_FAMILIES} {NETWORK_FAMILIES}")
    settings = [ln for ln in text.splitlines() if not ln.lstrip().startswith(("#", ";"))]
    left = [p for p in PLACEHOLDERS if any(p in ln for ln in settings)]
    assert not left, f"the unit template has a placeholder this code does not fill: {left}"
    return text


def unit_value(what: str, value: str) -> str:
    """``value`` if systemd reads it back as the same text, else ``UsageError`` (one line):
    a control character (a newline would start a new setting: an injected line), a line
    separator, or bytes that are not UTF-8 (a unit file is UTF-8)."""
    for char in value:
        category = unicodedata.category(char)
        if category == "Cs":
            raise UsageError(f"{what} {safe_file.shown(value)}: not valid UTF-8 text, which a "
                             "systemd unit cannot hold")
        if category in REFUSED_CATEGORIES:
            raise UsageError(f"{what} {value!r}: a control character (U+{ord(char):04X}) "
                             "cannot go into a systemd unit")
    return value


def systemd_word(word: str, *, program: bool = False) -> str:
    """One word of an Exec*= line (systemd.syntax(7), systemd.service(5) "Command lines"):
    specifiers (``%``) escaped by doubling, and variables (``$``) too except in the
    ``program`` (the first word, which systemd never substitutes: ``$$`` would stay two);
    quoted, with ``\\`` and ``"`` escaped, when it holds a blank, a quote or a backslash
    (systemd unescapes C-style sequences in every word)."""
    unit_value("a command-line word", word)
    if program and any(c in word for c in "\"'\\"):
        # systemd refuses such a program outright ("Executable name contains special
        # characters", string_is_safe()): no escaping makes it runnable.
        raise UsageError(f"{word}: systemd does not run a program whose path holds a quote or "
                         "a backslash; install jetbot_rt in a directory without one")
    word = word.replace("%", "%%")
    if not program:
        word = word.replace("$", "$$")
    if any(c in word for c in " \t\"'\\"):
        word = '"' + word.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return word


def _package_data(name: str) -> str:
    # pkgutil.get_data: Python 3.8 has no importlib.resources.files.
    data = pkgutil.get_data("jetbot_rt", f"data/{name}")
    assert data is not None  # the jetbot_rt package has a loader
    return data.decode("utf-8")


def unit_template() -> str:
    return _package_data(UNIT_NAME)


def default_config_text() -> str:
    return _package_data("default-config.toml")


def staged(root: Path, target: PurePosixPath) -> Path:
    """``target`` (absolute, on the target system) inside ``root``, or ``UsageError`` when the
    way there leaves ``root``: a ``..``, or a symbolic link in the staged tree (an image's
    absolute link means its own ``/``, which here is the host's)."""
    if ".." in target.parts:
        raise UsageError(f"{target}: must not contain '..'")
    path = root / target.relative_to("/")
    inside = root.resolve()
    existing = path
    while not os.path.lexists(existing) and existing != root:
        existing = existing.parent  # what does not exist yet is created under it
    resolved = existing.resolve()
    if resolved != inside and inside not in resolved.parents:
        raise UsageError(f"{path} leads outside --root {root} (to {resolved}, through a "
                         "symbolic link); nothing was written")
    return path


def read_text(path: Path, what: str) -> str:
    """A staged file we did not write (a unit, a passwd): bounded, never blocking."""
    return safe_file.read_text(path, what, FILE_LIMIT)


def write_file(path: Path, text: str) -> None:
    """Write via a new file renamed over ``path`` (a link planted there is replaced, not
    followed), mode 0644: systemd and the service user read it."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with safe_file.replaced_file(path.parent, path.name, 0o644) as fd:
            os.fchmod(fd, 0o644)  # whatever the umask
            data = text.encode("utf-8")
            while data:
                data = data[os.write(fd, data):]
    except OSError as exc:
        hint = " (run it with sudo)" if isinstance(exc, PermissionError) else ""
        raise UsageError(f"cannot write {path}: {exc.strerror or exc}{hint}") from None


def print_next_steps(root: Path, user: str, config: PurePosixPath, executable: Path) -> None:
    if root.resolve() != Path("/"):
        print(f"(staged under {root}; run these on the target once the tree is in place)")
    # Quoted for a shell: the commands are meant to be pasted.
    shown_config, shown_executable = shlex.quote(str(config)), shlex.quote(str(executable))
    steps = [
        (f"jetbot-rt check --config {shown_config}", "motor board, camera, policy"),
        ("sudo systemctl daemon-reload", ""),
        ("sudo systemctl enable --now jetbot-rt", "start now and at every boot"),
        ("systemctl status jetbot-rt", "state and the loop's STATUS= line"),
        ("journalctl -u jetbot-rt -f", "follow the log"),
        # absolute: a venv's bin/ is not on sudo's secure_path
        (f"sudo {shown_executable} stop --config {shown_config}",
         "stop the robot from any shell"),
    ]
    width = max(len(command) for command, _ in steps)
    print("next:")
    for command, comment in steps:
        print(f"  {command.ljust(width)}  # {comment}" if comment else f"  {command}")
    print(f"the service runs as {user!r}; it reads {config} and writes only "
          "/run/jetbot-rt, /var/log/jetbot-rt and /var/lib/jetbot-rt")
