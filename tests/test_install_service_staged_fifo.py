"""install-service reads the ``#!`` line of the staged program through safe_file: a FIFO (or a
device) at that path in a staged tree is not a program, and the install does not wait on it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

HANG_S = 60  # only catches a hang: the command takes about a second


def test_a_fifo_where_the_staged_program_goes_does_not_hang_the_install(tmp_path: Path) -> None:
    root = tmp_path / "image"
    program = root / "opt" / "jetbot-rt" / "bin" / "jetbot-rt"
    program.parent.mkdir(parents=True)
    os.mkfifo(program)
    done = subprocess.run(
        [sys.executable, "-c", "import sys; from jetbot_rt.cli import main; sys.exit(main())",
         "install-service", "--root", str(root), "--user",
         "jetbot", "--executable", "/opt/jetbot-rt/bin/jetbot-rt"],
        capture_output=True, text=True, timeout=HANG_S, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert (root / "etc" / "systemd" / "system" / "jetbot-rt.service").is_file()
