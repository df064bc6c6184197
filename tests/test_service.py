"""``jetbot-rt install-service`` into a staging root, the unit checked by systemd-analyze."""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path, PurePosixPath

import pytest

from jetbot_rt.cli import main
from jetbot_rt.commands import install_service as service
from jetbot_rt.config.sections import Config, load_config
from jetbot_rt.errors import UsageError

REPO = Path(__file__).resolve().parents[1]
UNIT = PurePosixPath("etc/systemd/system/jetbot-rt.service")
CONFIG = PurePosixPath("etc/jetbot-rt/config.toml")
needs_systemd_analyze = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed"
)


def install(root: Path, *extra: str, user: str = "root") -> int:
    return main(["install-service", "--root", str(root), "--user", user, *extra])


def systemd_verify(unit: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["systemd-analyze", "verify", "--man=no", str(unit)],
        capture_output=True, text=True, timeout=60,
    )


def unit_values(text: str, key: str) -> list[str]:
    return re.findall(rf"^{key}=(.*)$", text, flags=re.MULTILINE)


def test_install_writes_unit_and_default_config(tmp_path: Path, capsys):
    assert install(tmp_path) == 0
    unit = (tmp_path / UNIT).read_text()
    assert "@" not in "".join(line for line in unit.splitlines() if not line.startswith("#"))
    [exec_start] = unit_values(unit, "ExecStart")
    [exec_stop_post] = unit_values(unit, "ExecStopPost")
    executable = Path(exec_start.split()[0])
    assert executable.is_absolute() and os.access(executable, os.X_OK)
    assert executable.name == "jetbot-rt"
    assert exec_start == f"{executable} run --backend real --config /etc/jetbot-rt/config.toml"
    assert exec_stop_post == f"{executable} stop --config /etc/jetbot-rt/config.toml"
    assert unit_values(unit, "User") == ["root"]
    assert unit_values(unit, "Type") == ["notify"]
    assert unit_values(unit, "RuntimeDirectory") == ["jetbot-rt"]
    config = tmp_path / CONFIG
    assert config.read_text() == service.default_config_text()
    assert config.stat().st_mode & 0o777 == 0o644
    out = capsys.readouterr().out
    assert "systemctl daemon-reload" in out and "enable --now jetbot-rt" in out
    assert "journalctl -u jetbot-rt" in out


@needs_systemd_analyze
def test_installed_unit_passes_systemd_analyze_verify(tmp_path: Path):
    assert install(tmp_path) == 0
    result = systemd_verify(tmp_path / UNIT)
    assert result.returncode == 0, result.stderr
    assert result.stderr == "", "no warnings either (unknown keys, bad values)"


@needs_systemd_analyze
def test_systemd_analyze_verify_catches_a_broken_unit(tmp_path: Path):
    """The check above can fail: a typo in a key and a missing executable are reported."""
    assert install(tmp_path) == 0
    unit = tmp_path / UNIT
    text = unit.read_text().replace("NoNewPrivileges=", "NoNewPrivilege=")
    unit.write_text(text.replace("ExecStart=/", "ExecStart=/nonexistent/"))
    result = systemd_verify(unit)
    assert "NoNewPrivilege" in result.stderr
    assert result.returncode != 0


@needs_systemd_analyze
def test_executable_path_with_a_space_is_quoted(tmp_path: Path):
    installed = Path(sysconfig.get_path("scripts")) / "jetbot-rt"
    odd_dir = tmp_path / "my venv" / "bin"
    odd_dir.mkdir(parents=True)
    shutil.copy2(installed, odd_dir / "jetbot-rt")
    text = service.render_unit(odd_dir / "jetbot-rt", "root", PurePosixPath("/etc/a%b.toml"))
    assert f'ExecStart="{odd_dir}/jetbot-rt" run --backend real --config /etc/a%%b.toml' in text
    unit = tmp_path / "jetbot-rt.service"
    unit.write_text(text)
    result = systemd_verify(unit)
    assert result.returncode == 0 and result.stderr == "", result.stderr


def test_existing_config_is_never_overwritten(tmp_path: Path):
    config = tmp_path / CONFIG
    config.parent.mkdir(parents=True)
    config.write_text("[motors]\nlayout = \"adafruit_motorhat\"\n")
    assert install(tmp_path) == 0
    assert install(tmp_path, "--force") == 0
    assert config.read_text() == "[motors]\nlayout = \"adafruit_motorhat\"\n"


def test_existing_unit_needs_force(tmp_path: Path, capsys):
    unit = tmp_path / UNIT
    unit.parent.mkdir(parents=True)
    unit.write_text("[Service]\nExecStart=/bin/true\n")
    assert install(tmp_path) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--force" in err
    assert unit.read_text() == "[Service]\nExecStart=/bin/true\n"
    assert not (tmp_path / CONFIG).exists(), "nothing written after an error"
    assert install(tmp_path, "--force") == 0
    assert "Type=notify" in unit.read_text()
    assert install(tmp_path) == 0, "the same unit again is fine without --force"
    assert "unchanged" in capsys.readouterr().out


needs_systemd_sysusers = pytest.mark.skipif(
    shutil.which("systemd-sysusers") is None, reason="systemd-sysusers is not installed"
)
SYSUSERS = PurePosixPath("etc/sysusers.d/jetbot-rt.conf")


@needs_systemd_sysusers
def test_staging_needs_none_of_the_robots_users_and_sysusers_creates_them(tmp_path: Path):
    """The robot's user exists neither here nor in the staged tree: the unit is staged, and
    systemd-sysusers (as the robot runs it, here on the staged tree) creates the user and the
    groups of SupplementaryGroups=, Debian's missing i2c included."""
    root = tmp_path / "image"
    (root / "etc").mkdir(parents=True)
    (root / "etc" / "passwd").write_text("root:x:0:0:root:/root:/bin/bash\n")
    (root / "etc" / "group").write_text("root:x:0:\nvideo:x:44:\n")
    result = subprocess.run(
        [sys.executable, "-m", "jetbot_rt.cli", "install-service", "--root", str(root),
         "--user", "no-such-user-jetbot-rt"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert unit_values((root / UNIT).read_text(), "User") == ["no-such-user-jetbot-rt"]
    assert f"wrote {root / SYSUSERS}" in result.stdout
    next_steps = result.stdout.split("next:\n", 1)[1].splitlines()
    assert next_steps[0].split()[:3] == ["sudo", "systemd-sysusers", "/" + str(SYSUSERS)]
    applied = subprocess.run(["systemd-sysusers", f"--root={root}"], capture_output=True,
                             text=True, timeout=60)
    assert applied.returncode == 0, applied.stderr
    passwd = (root / "etc" / "passwd").read_text()
    assert "\nno-such-user-jetbot-rt:" in passwd
    groups = {line.split(":")[0]: line.split(":")[3].split(",")
              for line in (root / "etc" / "group").read_text().splitlines()}
    assert "no-such-user-jetbot-rt" in groups["i2c"] and "no-such-user-jetbot-rt" in groups["video"]
    assert groups["video"] and (root / "etc" / "group").read_text().count("video:x:44:") == 1


def test_a_program_the_staged_tree_lacks_or_tmp_holds_is_named_with_the_knob(tmp_path: Path):
    root = tmp_path / "image"
    root.mkdir()
    result = subprocess.run(
        [sys.executable, "-m", "jetbot_rt.cli", "install-service", "--root", str(root),
         "--user", "jetbot"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    [warning] = result.stderr.splitlines()
    assert warning.startswith("warning: the unit's ExecStart runs") and "--executable" in warning
    in_tmp = PurePosixPath("/tmp/venv/bin/jetbot-rt")
    assert main(["install-service", "--root", str(root), "--user", "jetbot", "--force",
                 "--executable", str(in_tmp)]) == 0
    assert unit_values((root / UNIT).read_text(), "ExecStart")[0].startswith(f"{in_tmp} run ")
    assert service.target_warnings(root, False, in_tmp, "jetbot")[0].count("PrivateTmp") == 1


@needs_systemd_analyze
def test_a_unit_staged_for_a_program_in_the_tree_passes_verify_on_that_tree(tmp_path: Path,
                                                                                capsys):
    """systemd-analyze --root reads ExecStart's program in the staged tree: what the robot
    will have, not what this workstation has."""
    root = tmp_path / "image"
    program = root / "opt" / "jetbot-rt" / "bin" / "jetbot-rt"
    program.parent.mkdir(parents=True)
    program.write_text("#!/opt/jetbot-rt/bin/python\n")
    program.chmod(0o755)
    shutil.copytree("/usr/lib/systemd/system", root / "usr" / "lib" / "systemd" / "system",
                    symlinks=True)
    assert main(["install-service", "--root", str(root), "--user", "jetbot", "--executable",
                 "/opt/jetbot-rt/bin/jetbot-rt"]) == 0
    assert capsys.readouterr().err == "", "nothing to warn about"
    unit = (root / UNIT).read_text()
    assert unit_values(unit, "ProtectHome") == ["yes"]
    verify = subprocess.run(["systemd-analyze", f"--root={root}", "verify", "--man=no",
                             str(root / UNIT)], capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0 and verify.stderr == "", verify.stderr
    program.unlink()
    verify = subprocess.run(["systemd-analyze", f"--root={root}", "verify", "--man=no",
                             str(root / UNIT)], capture_output=True, text=True, timeout=60)
    assert verify.returncode != 0 and "/opt/jetbot-rt/bin/jetbot-rt" in verify.stderr


@pytest.mark.parametrize("value", ["opt/jetbot-rt/bin/jetbot-rt", "/opt/../tmp/jetbot-rt",
                                   "/opt/jetbot-rt/bin/"])
def test_an_executable_that_is_no_absolute_file_path_is_refused(tmp_path: Path, capsys,
                                                                 value: str):
    assert main(["install-service", "--root", str(tmp_path), "--user", "jetbot",
                 "--executable", value]) == 2
    assert "--executable" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_unwritable_target_is_one_line_exit_2(tmp_path: Path, capsys):
    # Running as root, permissions cannot be taken away; a file where a directory must go can.
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc" / "systemd").write_text("not a directory")
    assert install(tmp_path) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot write" in err


@pytest.mark.parametrize(
    ("args", "message"),
    [(["--config", "relative.toml"], "absolute"), (["--root", "/nonexistent-root"], "directory")],
)
def test_bad_arguments_exit_2(tmp_path: Path, capsys, args: list[str], message: str):
    argv = ["install-service", "--user", "root", "--root", str(tmp_path), *args]
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_protect_home_is_relaxed_only_for_an_installation_in_a_home():
    etc_config = PurePosixPath("/etc/jetbot-rt/config.toml")
    package = PurePosixPath(Path(service.__file__).resolve())
    if any(home in package.parents for home in service.HOME_DIRS):
        pytest.skip("this checkout itself lives in a home directory")
    in_opt = service.render_unit(Path("/opt/jetbot-rt/bin/jetbot-rt"), "jetbot", etc_config)
    assert unit_values(in_opt, "ProtectHome") == ["yes"]
    in_home = service.render_unit(Path("/home/jetson/.local/bin/jetbot-rt"), "jetbot", etc_config)
    assert unit_values(in_home, "ProtectHome") == ["read-only"]
    config_in_home = PurePosixPath("/root/jetbot.toml")
    assert service.protect_home(Path("/opt/jetbot-rt/bin/jetbot-rt"), config_in_home) == "read-only"


def test_repository_unit_is_the_packaged_template():
    packaged = service.unit_template()
    unit = REPO / "systemd" / "jetbot-rt.service"
    # stored once: systemd/ links to the packaged template (the wheel carries jetbot_rt/data/)
    assert unit.is_symlink()
    assert unit.resolve() == (REPO / "jetbot_rt" / "data" / "jetbot-rt.service").resolve()
    assert unit.read_text() == packaged
    for placeholder in ("@EXECUTABLE@", "@USER@", "@CONFIG@", "@PROTECT_HOME@"):
        assert placeholder in packaged


def test_default_config_loads_to_the_defaults(tmp_path: Path):
    path = tmp_path / "config.toml"
    path.write_text(service.default_config_text())
    assert load_config(path) == Config()


def test_default_config_mentions_every_key():
    text = service.default_config_text()
    sections = re.split(r"^\[(\w+)\]$", text, flags=re.MULTILINE)
    keys_by_section = {
        name: set(re.findall(r"^#? ?(\w+) = ", body, flags=re.MULTILINE))
        for name, body in zip(sections[1::2], sections[2::2])
    }
    for section in dataclasses.fields(Config):
        declared = {f.name for f in dataclasses.fields(getattr(Config(), section.name))}
        assert declared <= keys_by_section.get(section.name, set()), section.name


# ---- hostile values and hostile trees ------------------------------------------------------


def installed_files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() or p.is_symlink())


@pytest.mark.parametrize(("option", "value"), [
    ("--config", "/etc/jetbot-rt/x.toml\nExecStartPre=/bin/touch /pwned"),
    ("--config", "/etc/jetbot-rt/x.toml\rExecStartPre=/bin/true"),
    ("--config", "/etc/jetbot-rt/\x1b[31mred.toml"),
    ("--config", "/etc/jetbot-rt/x\u2028y.toml"),
    ("--config", "/etc/jetbot-rt/\udcff.toml"),  # a byte that is not UTF-8, as argv gives it
    ("--config", "/etc/jetbot-rt/../../../outside/x.toml"),
    ("--config", "/etc/jetbot-rt/"),
    ("--user", "root\nExecStartPre=/bin/true"),
    ("--user", "%n"),
    ("--user", "ro ot"),
])
def test_a_value_systemd_would_read_otherwise_is_refused_in_one_line(
        tmp_path: Path, capsys, option: str, value: str) -> None:
    root = tmp_path / "root"
    root.mkdir()
    args = {"--user": "root", "--config": "/etc/jetbot-rt/config.toml", option: value}
    assert main(["install-service", "--root", str(root), *(x for kv in args.items() for x in kv)]
                ) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("jetbot-rt install-service: error:"), err
    assert installed_files(tmp_path) == [], "nothing written, inside --root or out"


def test_a_newline_in_the_executables_own_path_writes_no_unit(tmp_path: Path) -> None:
    """The executable's path is a value like any other: a venv in a directory whose name holds
    a newline would otherwise inject unit lines (hence the escaping)."""
    odd = tmp_path / "venv\nExecStartPre=/bin/touch pwned" / "bin"
    odd.mkdir(parents=True)
    script = odd / "jetbot-rt"
    shutil.copy2(Path(sysconfig.get_path("scripts")) / "jetbot-rt", script)
    root = tmp_path / "root"
    root.mkdir()
    result = subprocess.run([str(script), "install-service", "--root", str(root), "--user",
                             "root"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.count("\n") == 1 and "control character" in result.stderr
    assert list(root.iterdir()) == []


@pytest.mark.parametrize("link", ["etc", "etc/systemd/system", "etc/jetbot-rt",
                                  "etc/jetbot-rt/config.toml", "etc/sysusers.d"])
def test_a_symbolic_link_in_the_staged_tree_cannot_lead_out_of_root(tmp_path: Path, capsys,
                                                                   link: str) -> None:
    """An image's absolute link means the image's /, which here is the host's: refused, one
    line, and nothing is read or written where it points."""
    outside = tmp_path / "host"
    outside.mkdir()
    (outside / "passwd").write_text("root:x:0:0::/root:/bin/sh\n")
    root = tmp_path / "root"
    target = root / link
    target.parent.mkdir(parents=True, exist_ok=True)
    target.symlink_to(outside / "passwd" if link.endswith(("passwd", ".toml")) else outside)
    before = installed_files(outside)
    assert install(root) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "outside --root" in err, err
    assert installed_files(outside) == before
    assert (outside / "passwd").read_text() == "root:x:0:0::/root:/bin/sh\n"


def test_a_link_inside_root_at_the_unit_is_replaced_not_followed(tmp_path: Path) -> None:
    root = tmp_path / "root"
    unit = root / UNIT
    unit.parent.mkdir(parents=True)
    decoy = root / "etc" / "decoy"
    decoy.write_text("decoy\n")
    unit.symlink_to(decoy)
    assert install(root, "--force") == 0
    assert not unit.is_symlink() and "Type=notify" in unit.read_text()
    assert decoy.read_text() == "decoy\n"


ODD_NAMES = ["my venv", "100%", "$HOME", "${HOME}", "semi;colon", "été", "a  two  spaces",
             "%n%%", "{}*?[]", "#hash", "tab-less;and=equals"]
REFUSED_IN_PROGRAMS = ["back\\slash", 'dou"ble', "sin'gle", "end\\"]


@needs_systemd_analyze
def test_every_odd_character_in_a_path_reaches_systemd_unchanged(tmp_path: Path) -> None:
    """Each odd directory name holds a real copy of the executable; systemd-analyze verify
    fails on an ExecStart= whose path does not exist, so it passes only if systemd reads back
    exactly the path that was escaped."""
    installed = Path(sysconfig.get_path("scripts")) / "jetbot-rt"
    for index, name in enumerate(ODD_NAMES):
        directory = tmp_path / f"{index}" / name
        directory.mkdir(parents=True)
        executable = directory / "jetbot-rt"
        shutil.copy2(installed, executable)
        unit = tmp_path / f"odd{index}.service"
        unit.write_text(service.render_unit(executable, "root",
                                            PurePosixPath(f"/etc/{name}/c.toml")))
        result = systemd_verify(unit)
        assert result.returncode == 0 and result.stderr == "", (name, result.stderr)
        broken = unit.read_text().replace(service.systemd_word(str(executable), program=True),
                                          f'"{executable}x"', 1)
        unit.write_text(broken)
        assert systemd_verify(unit).returncode != 0, "verify would not notice a wrong path"


@pytest.mark.parametrize("name", REFUSED_IN_PROGRAMS)
def test_a_program_path_systemd_refuses_to_run_is_refused_in_one_line(tmp_path: Path,
                                                                      name: str) -> None:
    """systemd will not run a program whose path holds a quote or a backslash, however it is
    escaped ("Executable name contains special characters"): say so instead of writing a unit
    that cannot start. In an argument (the config's path) they are escaped."""
    with pytest.raises(UsageError, match="quote or a backslash") as refused:
        service.render_unit(tmp_path / name / "jetbot-rt", "root",
                            PurePosixPath("/etc/jetbot-rt/config.toml"))
    assert "\n" not in str(refused.value)
    text = service.render_unit(Path("/opt/jetbot-rt/bin/jetbot-rt"), "root",
                               PurePosixPath(f"/etc/{name}/c.toml"))
    [exec_start] = unit_values(text, "ExecStart")
    word = exec_start.split(" --config ", 1)[1]
    assert word.startswith('"') and word.endswith('"'), word
    assert re.sub(r"\\(.)", r"\1", word[1:-1]) == f"/etc/{name}/c.toml"


def test_placeholders_are_filled_in_the_settings_and_nowhere_else(tmp_path: Path) -> None:
    assert install(tmp_path) == 0
    text = (tmp_path / UNIT).read_text()
    comments = "".join(ln for ln in text.splitlines(keepends=True) if ln.startswith("#"))
    settings = "".join(ln for ln in text.splitlines(keepends=True) if not ln.startswith("#"))
    assert "fills in @EXECUTABLE@, @USER@, @CONFIG@ and\n# @PROTECT_HOME@" in comments
    assert comments == "".join(ln for ln in service.unit_template().splitlines(keepends=True)
                               if ln.startswith("#")), "comments as the template has them"
    assert "@" not in settings


# ---- what the unit decides -----------------------------------------------------------------


def test_an_orderly_end_or_a_fault_is_never_restarted_whatever_exec_stop_post_says():
    """systemd (service_shall_restart, src/core/service.c) checks RestartPreventExitStatus=
    first, against the main process's exit code only, and then Restart=. An ExecStopPost that
    fails (exit 1: the board not confirmed off), times out or is killed turns the unit's result
    into exit-code, timeout or signal; the main process's 0, 2 or 3 still prevents a restart,
    and so does its death by the FinalKillSignal (a watchdog kill is the same fault as the
    exit 3 the watchdog signal ends in when Python still runs). ExecStopPost keeps no '-': its
    failure shows as a failed unit."""
    text = service.unit_template()
    assert unit_values(text, "Restart") == ["on-abnormal"]
    [final_kill] = unit_values(text, "FinalKillSignal")
    assert set(unit_values(text, "RestartPreventExitStatus")[0].split()) == {
        "0", "2", "3", final_kill}
    [stop_post] = unit_values(text, "ExecStopPost")
    assert stop_post.startswith("@EXECUTABLE@ stop"), "no '-' or other prefix"
    assert unit_values(text, "StartLimitBurst") == ["3"]


def test_the_runtime_directory_is_private_and_the_service_runs_ahead_of_the_load():
    text = service.unit_template()
    assert unit_values(text, "RuntimeDirectoryMode") == ["0700"]
    [nice] = unit_values(text, "Nice")
    assert -20 <= int(nice) < 0
    assert not unit_values(text, "CPUSchedulingPolicy"), "decided: no real-time policy"


def test_the_printed_next_steps_paste_into_a_shell(tmp_path: Path) -> None:
    odd = tmp_path / "my venv" / "bin"
    odd.mkdir(parents=True)
    script = odd / "jetbot-rt"
    shutil.copy2(Path(sysconfig.get_path("scripts")) / "jetbot-rt", script)
    root = tmp_path / "root"
    root.mkdir()
    result = subprocess.run([str(script), "install-service", "--root", str(root), "--user",
                             "root", "--config", "/etc/jet bot/config.toml"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert f"sudo '{script}' stop --config '/etc/jet bot/config.toml'" in result.stdout
