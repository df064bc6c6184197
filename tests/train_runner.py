"""Run ``jetbot-train`` as a user would (the console script, a subprocess) or, where an
interpreter and torch start per case (3-5 s) would dominate, in this process."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

JETBOT_TRAIN = shutil.which("jetbot-train") or str(Path(sys.executable).parent / "jetbot-train")


def train_cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([JETBOT_TRAIN, *args], capture_output=True, text=True, timeout=timeout)


def train_main(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """``jetbot-train ARGS`` in this process: the exit code (argparse's SystemExit
    included), stdout and stderr."""
    from jetbot_rt.train.cli import main

    try:
        code = main(list(args))
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err  # type: ignore[return-value]


def train_here(capsys: pytest.CaptureFixture[str], *args: str) -> subprocess.CompletedProcess:
    """``train_main`` shaped as ``train_cli``'s result."""
    code, out, err = train_main(capsys, *args)
    return subprocess.CompletedProcess(args, code, out, err)
