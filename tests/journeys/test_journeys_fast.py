"""The documented journeys that take seconds, run from the docs' own commands (read at test
time: doc_commands.py) in this suite's venv: drive the simulator, stage the service for the
robot and verify it with systemd's own tools. And every journey's commands, the long ones'
too, are still in their docs. The rest: test_journeys_long.py (``pytest -m long``)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from doc_commands import (
    BIN,
    INLINE,
    JOURNEYS,
    PYTHON_BLOCKS,
    TOML_BLOCKS,
    command,
    inline,
    ok,
    python_block,
    sh,
    toml_block,
    with_knobs,
)

needs_systemd = pytest.mark.skipif(
    not (shutil.which("systemd-analyze") and shutil.which("systemd-sysusers")),
    reason="systemd-analyze and systemd-sysusers are not installed")


def test_every_journeys_commands_are_still_in_their_docs() -> None:
    """A doc edit that drops, renames or moves a command a journey runs fails here, in the
    fast suite, long journeys included."""
    for commands in JOURNEYS.values():
        for doc, start in commands:
            command(doc, start)
    for blocks in PYTHON_BLOCKS.values():
        for doc, containing in blocks:
            python_block(doc, containing)
    for blocks in TOML_BLOCKS.values():
        for doc, containing in blocks:
            toml_block(doc, containing)
    for texts in INLINE.values():
        for doc, text in texts:
            inline(doc, text)


def test_drive_the_simulator_as_the_readme_says(tmp_path: Path) -> None:
    """The README's first command, its last step (the install is the long journey's: a fresh
    clone's fresh venv); `.venv` here is this suite's venv."""
    first = command("README.md", JOURNEYS["drive the simulator (README)"][0][1])
    drive = first.split(" && ")[-1]
    assert drive.startswith(".venv/bin/jetbot-rt run --backend sim")
    (tmp_path / ".venv").symlink_to(BIN.parent)
    proc = ok(sh(with_knobs(drive, {"--duration 20": "--duration 1"}), tmp_path))
    assert "driving at 30 Hz" in proc.stdout
    assert "from the goal block" in proc.stdout and "exit code    0" in proc.stdout


@needs_systemd
def test_stage_the_service_for_the_robot_and_verify_it_as_docs_robot_says(
        tmp_path: Path) -> None:
    """An SD-card image (its passwd and group, systemd's units, the runtime in /opt) staged
    with the doc's commands: the user exists in the image and the unit verifies against it."""
    image = tmp_path / "image"
    (image / "etc").mkdir(parents=True)
    (image / "etc" / "passwd").write_text("root:x:0:0:root:/root:/bin/bash\n")
    (image / "etc" / "group").write_text("root:x:0:\nvideo:x:44:\n")
    shutil.copytree("/usr/lib/systemd/system", image / "usr" / "lib" / "systemd" / "system",
                    symlinks=True)
    program = image / "opt" / "jetbot-rt" / "bin" / "jetbot-rt"
    program.parent.mkdir(parents=True)
    program.write_text("#!/opt/jetbot-rt/bin/python\n")
    program.chmod(0o755)
    knobs = {"/mnt/jetbot": str(image)}
    steps = JOURNEYS["stage the service for the robot (docs/ROBOT.md)"]
    install, sysusers, verify = (with_knobs(command(doc, start), knobs) for doc, start in steps)
    staged = ok(sh(install, tmp_path))
    assert staged.stderr == "", "nothing the robot lacks"
    assert "sudo systemd-sysusers /etc/sysusers.d/jetbot-rt.conf" in staged.stdout
    ok(sh(sysusers, tmp_path))
    assert any(line.startswith("jetbot:") for line in
               (image / "etc" / "passwd").read_text().splitlines())
    checked = ok(sh(verify, tmp_path))
    assert checked.stderr == "", checked.stderr
    assert os.access(program, os.X_OK)
