"""What the robot installs: the robot side needs no Python newer than 3.8 (JetPack 4.6's
python3.8), and the wheel built on a workstation carries everything the robot needs."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "jetbot_rt"
# Python 3.10+ only: the simulator and the trainer (never imported on the robot).
WORKSTATION_ONLY = ("sim", "train")


def robot_side_modules() -> list[Path]:
    return sorted(
        path for path in PACKAGE.rglob("*.py")
        if path.relative_to(PACKAGE).parts[0] not in WORKSTATION_ONLY
    )


def vermin(*paths: Path) -> subprocess.CompletedProcess[str]:
    script = Path(sys.executable).with_name("vermin")  # vermin has no __main__
    return subprocess.run(
        [str(script), "--target=3.8-", "--violations", "--no-tips",
         "--no-parse-comments", *map(str, paths)],
        capture_output=True, text=True, timeout=120,
    )


def test_robot_side_needs_no_python_newer_than_3_8():
    modules = robot_side_modules()
    assert PACKAGE / "hal" / "motors.py" in modules
    assert not any("sim" in m.parts or "train" in m.parts for m in modules)
    result = vermin(*modules)
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_3_8_check_catches_what_3_8_lacks(tmp_path):
    source = tmp_path / "newer.py"
    source.write_text("def f(a, b):\n    return list(zip(a, b, strict=True))\n")
    result = vermin(source)
    assert result.returncode != 0
    assert "zip(strict)" in result.stdout


def build_wheel(out: Path) -> Path:
    """Build from a copy of the checkout (no build/ or egg-info left in the tree)."""
    source = out / "src"
    shutil.copytree(
        REPO, source,
        ignore=shutil.ignore_patterns(
            ".git", ".venv", "build", "dist", "runs", "*.egg-info", "__pycache__", ".*_cache"
        ),
    )
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(out), str(source)],
        check=True, capture_output=True, text=True, timeout=300,
    )
    (wheel,) = out.glob("jetbot_rt-*.whl")
    return wheel


@pytest.mark.slow
def test_wheel_carries_policies_assets_and_unit_template(tmp_path):
    wheel = build_wheel(tmp_path)
    names = set(zipfile.ZipFile(wheel).namelist())
    wanted = [
        "jetbot_rt/policies/forward.onnx",
        "jetbot_rt/data/jetbot-rt.service",
        "jetbot_rt/data/default-config.toml",
        "jetbot_rt/hal/motors.py",
    ] + [
        f"jetbot_rt/sim/assets/{p.name}" for p in (PACKAGE / "sim" / "assets").iterdir()
    ]
    assert "jetbot_rt/sim/assets/jetbot.urdf" in wanted
    missing = [name for name in wanted if name not in names]
    assert not missing, f"not in {wheel.name}: {missing}"
    assert not any(name.startswith("tests/") for name in names)
    metadata = next(n for n in names if n.endswith(".dist-info/METADATA"))
    text = zipfile.ZipFile(wheel).read(metadata).decode()
    assert "Requires-Python: >=3.8" in text
