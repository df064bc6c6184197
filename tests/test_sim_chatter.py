"""PyBullet's C-level chatter is dropped, its real problems still reach stderr, and what
Python prints meanwhile is untouched; the GUI's no-display error names the cure."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("pybullet")

SCRIPT = """
import os
from jetbot_rt.sim.native_output import pybullet_chatter_filtered
from jetbot_rt.sim.pybullet_import import import_pybullet
p = import_pybullet()
with pybullet_chatter_filtered() as lines:
    os.write(1, b"startThreads creating 1 threads.\\nGL_VENDOR=Mesa/X.org\\n")
    print("ours, on stdout")
    c = p.connect(p.DIRECT)
    try:
        p.loadURDF("no-such-robot.urdf", physicsClientId=c)
    except p.error as exc:
        print("raised:", exc)
print(len(lines))
"""


def test_chatter_is_dropped_and_a_missing_file_still_said_on_stderr() -> None:
    proc = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == ["ours, on stdout", "raised: Cannot load URDF file.",
                                        "4"]
    assert "URDF file 'no-such-robot.urdf' not found" in proc.stderr
    assert all(line.startswith("pybullet: ") for line in proc.stderr.splitlines())
    assert "GL_VENDOR" not in proc.stderr and "startThreads" not in proc.stderr


def test_gui_without_a_display_names_xvfb_run(monkeypatch) -> None:
    from jetbot_rt.errors import UsageError
    from jetbot_rt.sim.config import SimConfig
    from jetbot_rt.sim.world import JetbotWorld

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(UsageError, match="xvfb-run -a jetbot-rt"):
        JetbotWorld(SimConfig(), gui=True)


def test_a_closed_stdout_stays_closed_and_nothing_breaks() -> None:
    script = ("import os, sys\n"
              "from jetbot_rt.sim.native_output import pybullet_chatter_filtered\n"
              "with pybullet_chatter_filtered():\n"
              "    os.write(2, b'through\\n')\n"
              "try:\n    os.fstat(1)\nexcept OSError:\n    print('closed', file=sys.stderr)\n")
    proc = subprocess.run(["bash", "-c", f'"{sys.executable}" -c "$0" >&-', script],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stderr.split() == ["through", "closed"], proc.stderr
