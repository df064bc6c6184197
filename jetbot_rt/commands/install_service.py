"""``jetbot-rt install-service``: write the systemd unit, a sysusers.d file for its user and,
if absent, a default config.

Everything is checked before anything is written, so an error (exit 2, one line) leaves the
target tree as it was. ``--root`` installs into a staging tree (an SD-card image, a test):
every path it reads or writes stays inside that tree (no ``..``, no symbolic link that leads
out). Every value that goes into the unit is refused when systemd could read it as something
else (a control character, text that is not UTF-8, a user name systemd would not take) and
escaped as systemd.syntax(7) says otherwise (quotes, ``%%``, ``$$``).

The service's user is declared, not required: ``etc/sysusers.d/jetbot-rt.conf`` names the user
and its groups, and ``systemd-sysusers`` creates what is missing on the robot (or in an image,
with ``--root``). Staging on a workstation therefore needs none of the robot's users here, and
the groups the unit's ``SupplementaryGroups=`` names exist once it ran (a missing one fails the
start with 216/GROUP). Checking the user when the service starts would not help: systemd
already refuses a missing ``User=`` (217/USER), on the robot, with nobody at a shell.
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
SYSUSERS_DIR = PurePosixPath("/etc/sysusers.d")
SYSUSERS_NAME = "jetbot-rt.conf"
APPLY_SYSUSERS = f"sudo systemd-sysusers {SYSUSERS_DIR / SYSUSERS_NAME}"
SUPPLEMENTARY_GROUPS = ("i2c", "video")
"""The unit's SupplementaryGroups=: i2c owns /dev/i2c-N (JetPack's udev rules; on Debian and
Ubuntu the i2c-tools package adds the group and the rule), video the camera. The JetBot image
also has gpio, which nothing here uses (the motors are on I2C)."""
I2C_GROUP_HINT = ("on Debian/Ubuntu `sudo apt-get install i2c-tools` adds group i2c and the udev "
                  "rule that gives it /dev/i2c-N (JetPack has both)")
# Where the service cannot find its program: PrivateTmp=yes gives it an empty /tmp, and both
# are emptied at boot.
TEMPORARY_DIRS = (PurePosixPath("/tmp"), PurePosixPath("/var/tmp"))
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
        help=f"the unprivileged user the service runs as (default {DEFAULT_USER}); declared "
        f"in {SYSUSERS_DIR / SYSUSERS_NAME} with its groups ({', '.join(SUPPLEMENTARY_GROUPS)}) "
        f"for systemd-sysusers to create on the robot: {APPLY_SYSUSERS}",
    )
    parser.add_argument(
        "--executable", metavar="PATH",
        help="the jetbot-rt program as seen on the target, for ExecStart (default: the one "
        "running this command); with --root, e.g. /opt/jetbot-rt/bin/jetbot-rt",
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
    check_user_name(args.user)
    on_target = root.resolve() == Path("/")
    executable, script = target_executable(root, args.executable, on_target)

    unit_path = staged(root, UNIT_DIR / UNIT_NAME)
    sysusers_path = staged(root, SYSUSERS_DIR / SYSUSERS_NAME)
    config_path = staged(root, config)
    monitor = None
    if config_path.exists() or config_path.is_symlink():
        from jetbot_rt.config.sections import load_config

        # an existing config is kept: it must be one the service reads
        monitor = load_config(config_path).monitor.listen
    unit_text = render_unit(executable, args.user, config, network=monitor is not None,
                            script=script)
    outputs = [(unit_path, unit_text, "the unit")]
    if args.user != "root":  # root exists everywhere, and needs no group
        outputs.append((sysusers_path, sysusers_text(args.user), "the sysusers.d file"))
    actions = [replace_action(path, text, what, args.force) for path, text, what in outputs]
    for (path, text, _), action in zip(outputs, actions):
        if action != "unchanged":
            write_file(path, text)
    config_action = "kept existing"
    if not config_path.exists():
        write_file(config_path, default_config_text())
        config_action = "wrote default"

    for (path, _, _), action in zip(outputs, actions):
        print(f"{action} {path}")
    print(f"{config_action} {config_path}")
    for line in target_warnings(root, on_target, executable, args.user):
        print(f"warning: {line}", file=sys.stderr)
    if monitor is not None:
        print(f"note: [monitor] listen = {monitor!r} in the config, so the unit allows IP "
              f"sockets ({NETWORK_FAMILIES}); without it, only local ones")
    if protect_home(executable, config, script) != "yes":
        print("note: this installation lives under /home or /root, so the unit uses "
              "ProtectHome=read-only; a venv in /opt/jetbot-rt keeps home directories hidden")
    print_next_steps(root, args.user, config, executable)
    return 0


def replace_action(path: Path, text: str, what: str, force: bool) -> str:
    """``wrote``, ``unchanged`` or ``replaced``; ``UsageError`` for a file that differs
    without ``--force``."""
    if not (path.exists() or path.is_symlink()):
        return "wrote"
    if read_text(path, what) == text:
        return "unchanged"
    if not force:
        raise UsageError(f"{path} exists and differs; pass --force to replace it")
    return "replaced"


def sysusers_text(user: str) -> str:
    """sysusers.d(5) lines for the service's user and its groups; ``u`` and ``m`` only, which
    every systemd since 215 reads (JetPack 4.6 has 237). An existing user or group is left as
    it is; ``m`` creates a missing group."""
    groups = "".join(f"m {user} {group}\n" for group in SUPPLEMENTARY_GROUPS)
    return (
        "# Written by `jetbot-rt install-service`: the user the jetbot-rt service runs as and the\n"
        "# groups of its SupplementaryGroups= (i2c: /dev/i2c-N, video: the camera). Apply on the\n"
        f"# robot with: {APPLY_SYSUSERS}\n"
        f'u {user} - "jetbot_rt service"\n{groups}'
    )


def target_warnings(root: Path, on_target: bool, executable: PurePosixPath, user: str) -> list[str]:
    """What the robot will not have: the program (outside the staged tree, or in a temporary
    directory the service cannot see), the user, the I2C group."""
    lines = []
    if any(tmp == executable or tmp in executable.parents for tmp in TEMPORARY_DIRS):
        lines.append(f"the unit's ExecStart runs {executable}, in a temporary directory: the "
                     "service's PrivateTmp=yes hides it and a reboot empties it; install "
                     "jetbot_rt in /opt/jetbot-rt (README) or pass --executable PATH")
    elif not on_target and not os.path.lexists(root / executable.relative_to("/")):
        lines.append(f"the unit's ExecStart runs {executable}, which is not in the staged tree "
                     f"{root}: install jetbot_rt there (e.g. a venv in /opt/jetbot-rt) or pass "
                     "--executable with the path it has on the robot")
    if on_target and user != "root":
        if not user_exists(user):
            lines.append(f"user {user!r} does not exist yet: {APPLY_SYSUSERS} creates it")
        try:
            grp.getgrnam("i2c")
        except KeyError:
            lines.append(f"group 'i2c' does not exist here; {I2C_GROUP_HINT}")
    return lines


def user_exists(name: str) -> bool:
    try:
        pwd.getpwnam(name)
    except KeyError:
        return False
    return True


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


def check_user_name(name: str) -> None:
    """A name the unit and sysusers.d can take; whether the user exists is the robot's
    business (the sysusers.d file creates it there)."""
    if USER_NAME.fullmatch(name) is None:
        raise UsageError(f"--user {name!r}: not a user name a systemd unit can take "
                         "(letters, digits, '_', '.', '-'; at most 32)")


def target_executable(root: Path, value: str | None,
                      on_target: bool) -> tuple[PurePosixPath, Path | None]:
    """ExecStart's program as the target sees it, and the file here to read its ``#!`` line
    from: None for this installation's own program (``protect_home``'s default), the staged
    file, or a path that does not exist when the staged tree does not have it yet."""
    if value is None:
        return PurePosixPath(find_executable()), None
    program = PurePosixPath(unit_value("--executable", value))
    if not program.is_absolute() or ".." in program.parts or value.endswith("/"):
        raise UsageError(f"--executable {value}: must be an absolute path of a file on the "
                         "target, without '..'")
    here = staged(root, program)
    if here.is_file():
        return program, here
    if on_target:
        raise UsageError(f"--executable {value}: no such file")
    return program, here


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


def protect_home(executable: Path | PurePosixPath, config: PurePosixPath,
                 script: Path | None = None) -> str:
    """``yes`` unless the program (as the target sees it), its interpreter (read from
    ``script``, the program's file here: by default the program itself, which is then this
    installation, so the package running now counts too) or its config lives in a home
    directory."""
    paths = [PurePosixPath(executable), config]
    if script is None:
        script = Path(executable)
        paths.append(PurePosixPath(Path(__file__).resolve()))
    interpreter = shebang_interpreter(script)
    if interpreter is not None:
        paths.append(interpreter)
    in_home = any(home == path or home in path.parents for path in paths for home in HOME_DIRS)
    return "read-only" if in_home else "yes"


def shebang_interpreter(executable: Path) -> PurePosixPath | None:
    try:  # the staged tree's file: a FIFO or a device there must not hang the install
        with open(safe_file.open_regular(executable, "program"), "rb") as script:
            first = script.readline(512)
    except (OSError, UsageError):
        return None
    if not first.startswith(b"#!"):
        return None
    words = first[2:].decode(errors="replace").split()
    return PurePosixPath(words[0]) if words else None


def render_unit(executable: Path | PurePosixPath, user: str, config: PurePosixPath, *,
                network: bool = False, script: Path | None = None) -> str:
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
        "@PROTECT_HOME@": protect_home(executable, config, script),
    }
    lines = []
    for line in unit_template().splitlines(keepends=True):
        if not line.lstrip().startswith(("#", ";")):
            for placeholder, value in values.items():
                line = line.replace(placeholder, value)
        lines.append(line)
    text = "".join(lines)
    assert f"SupplementaryGroups={' '.join(SUPPLEMENTARY_GROUPS)}\n" in text, \
        "the unit template's groups changed: SUPPLEMENTARY_GROUPS declares them to sysusers.d"
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


def print_next_steps(root: Path, user: str, config: PurePosixPath,
                     executable: PurePosixPath) -> None:
    if root.resolve() != Path("/"):
        print(f"(staged under {root}; run these on the target once the tree is in place)")
    # Quoted for a shell: the commands are meant to be pasted.
    shown_config, shown_executable = shlex.quote(str(config)), shlex.quote(str(executable))
    steps = [] if user == "root" else [(APPLY_SYSUSERS, f"creates user {user} and its groups")]
    steps += [
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
    if user != "root":
        print(f"the I2C bus: {I2C_GROUP_HINT}")
