"""What the workstation-only parts need (Python 3.10+, pybullet), said in one line.

pybullet publishes wheels for CPython 3.10 and 3.11 only; the ``sim`` and ``train`` extras
install it only there (no silent 80 MB source build on 3.12+), and this module names the fix.
"""

from __future__ import annotations

import importlib.util
import sys

SIM_PYTHONS = ((3, 10), (3, 11))
VENV_COMMAND = (
    "uv venv -p 3.11 .venv311 && uv pip install -p .venv311 -e '.[sim]'"
    " (or python3.11 -m venv .venv311 && .venv311/bin/pip install -e '.[sim]')"
)


def this_python() -> str:
    return f"{sys.version_info[0]}.{sys.version_info[1]}"


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ValueError:  # sys.modules[module] is None: blocked, as good as absent
        return False


def sim_problem() -> str | None:
    """None when the simulator can run here, else one line saying what to do."""
    if sys.version_info < (3, 10):
        return (
            f"the simulator and the trainer need Python 3.10 or newer (this is {this_python()});"
            " run them on a workstation"
        )
    if not _installed("pybullet"):
        if sys.version_info[:2] not in SIM_PYTHONS:
            return (
                f"pybullet has no wheel for Python {this_python()} (only 3.10 and 3.11); "
                f"use a Python 3.11 venv: {VENV_COMMAND}"
            )
        return "pybullet is not installed: pip install -e '.[sim]' (the sim extra)"
    return None
