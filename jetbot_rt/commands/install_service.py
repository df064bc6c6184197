"""``jetbot-rt install-service``: write the systemd unit and, if absent, a default config.

Everything is checked before anything is written, so an error (exit 2, one line) leaves the
target tree as it was. ``--root`` installs into a staging tree (an SD-card image, a test).
"""

from __future__ import annotations

import argparse
import contextlib
import grp
import os
import pkgutil
import pwd
import shutil
import sys
import sysconfig
from pathlib import Path, PurePosixPath

from jetbot_rt.errors import UsageError

UNIT_NAME = "jetbot-rt.service"
UNIT_DIR = PurePosixPath("/etc/systemd/system")
DEFAULT_CONFIG = "/etc/jetbot-rt/config.toml"
DEFAULT_USER = "jetbot"
CREATE_USER_HINT = "sudo useradd --system --groups i2c,video jetbot"
SUPPLEMENTARY_GROUPS = ("i2c", "video")
# ProtectHome=yes hides these; an installation living there needs ProtectHome=read-only.
HOME_DIRS = (PurePosixPath("/home"), PurePosixPath("/root"), PurePosixPath("/run/user"))


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
    root = Path(args.root)
    if not root.is_dir():
        raise UsageError(f"--root {args.root}: not a directory")
    config = PurePosixPath(args.config)
    if not config.is_absolute():
        raise UsageError(f"--config {args.config}: must be an absolute path on the target")
    check_user(args.user, root)
    executable = find_executable()

    unit_text = render_unit(executable, args.user, config)
    unit_path = staged(root, UNIT_DIR / UNIT_NAME)
    config_path = staged(root, config)
    if config_path.exists() or config_path.is_symlink():
        from jetbot_rt.config import load_config

        load_config(config_path)  # an existing config is kept: it must be one the service reads
    unit_action = "wrote"
    if unit_path.exists():
        if read_text(unit_path) == unit_text:
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
    if protect_home(executable, config) != "yes":
        print("note: this installation lives under /home or /root, so the unit uses "
              "ProtectHome=read-only; a venv in /opt/jetbot-rt keeps home directories hidden")
    print_next_steps(root, args.user, config, executable)
    return 0


def check_user(name: str, root: Path) -> None:
    """The user must exist on the target: the host's user database, or the staged
    ``etc/passwd`` when installing into another tree that has one."""
    passwd = root / "etc" / "passwd"
    if root.resolve() != Path("/") and passwd.is_file():
        names = {line.split(":", 1)[0] for line in read_text(passwd).splitlines()}
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


def render_unit(executable: Path, user: str, config: PurePosixPath) -> str:
    text = unit_template()
    values = {
        "@EXECUTABLE@": systemd_word(str(executable)),
        "@USER@": user,
        "@CONFIG@": systemd_word(str(config)),
        "@PROTECT_HOME@": protect_home(executable, config),
    }
    for placeholder, value in values.items():
        text = text.replace(placeholder, value)
    return text


def systemd_word(word: str) -> str:
    """One argument of an Exec*= line: ``%`` and ``$`` escaped, quoted if it has blanks."""
    word = word.replace("%", "%%").replace("$", "$$")
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
    return root / target.relative_to("/")


def read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        raise UsageError(f"cannot read {path}: {exc.strerror or exc}") from None


def write_file(path: Path, text: str) -> None:
    """Write via a temporary file and rename, mode 0644: systemd and the service user read it."""
    temporary = path.with_name(f".{path.name}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary.write_text(text, encoding="utf-8")
        temporary.chmod(0o644)
        os.replace(temporary, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            temporary.unlink(missing_ok=True)
        hint = " (run it with sudo)" if isinstance(exc, PermissionError) else ""
        raise UsageError(f"cannot write {path}: {exc.strerror or exc}{hint}") from None


def print_next_steps(root: Path, user: str, config: PurePosixPath, executable: Path) -> None:
    if root.resolve() != Path("/"):
        print(f"(staged under {root}; run these on the target once the tree is in place)")
    steps = [
        (f"jetbot-rt check --config {config}", "motor board, camera, policy"),
        ("sudo systemctl daemon-reload", ""),
        ("sudo systemctl enable --now jetbot-rt", "start now and at every boot"),
        ("systemctl status jetbot-rt", "state and the loop's STATUS= line"),
        ("journalctl -u jetbot-rt -f", "follow the log"),
        # absolute: a venv's bin/ is not on sudo's secure_path
        (f"sudo {executable} stop --config {config}", "stop the robot from any shell"),
    ]
    width = max(len(command) for command, _ in steps)
    print("next:")
    for command, comment in steps:
        print(f"  {command.ljust(width)}  # {comment}" if comment else f"  {command}")
    print(f"the service runs as {user!r}; it reads {config} and writes only "
          "/run/jetbot-rt, /var/log/jetbot-rt and /var/lib/jetbot-rt")
