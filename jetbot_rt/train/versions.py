"""The versions a figure was made with: what ``jetbot-train eval --json`` and the benchmark
scripts (``benchmarks/versions.py``) write beside their numbers, so a documented figure names
the stack that produced it (a seek policy scored 98 % and then 97 % after opencv and
onnxruntime moved on). Read from the installed distributions' metadata: nothing is imported
(torch alone takes seconds)."""

from __future__ import annotations

import platform
import subprocess
from importlib import metadata
from pathlib import Path

DISTRIBUTIONS = {
    "numpy": ("numpy",),
    "torch": ("torch",),
    "onnxruntime": ("onnxruntime", "onnxruntime-gpu"),
    "opencv": ("opencv-python-headless", "opencv-python", "opencv-contrib-python"),
    "pybullet": ("pybullet",),
    "gymnasium": ("gymnasium",),
    "jetbot_rt": ("jetbot_rt",),
}
"""The name a results file shows, and the distributions that provide it (the first
installed one counts)."""


def installed(names: tuple[str, ...]) -> str | None:
    for name in names:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return None


def git_commit(directory: Path) -> str | None:
    """``directory``'s checkout at HEAD, with ``-dirty`` when tracked files differ from it;
    None outside a git checkout (an installed wheel) or without git."""
    try:
        head = subprocess.run(["git", "-C", str(directory), "rev-parse", "HEAD"],
                              capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(directory), "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True,
                               timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


def versions() -> dict[str, str | None]:
    """python, numpy, torch, onnxruntime, opencv, pybullet, gymnasium, jetbot_rt (None where
    not installed) and ``git``: the commit of the checkout jetbot_rt runs from."""
    found: dict[str, str | None] = {"python": platform.python_version()}
    found.update({key: installed(names) for key, names in DISTRIBUTIONS.items()})
    found["git"] = git_commit(Path(__file__).resolve().parents[2])
    return found
