"""What the robot installs: the robot side needs no Python newer than 3.8 (JetPack 4.6's
python3.8), and the wheel built on a workstation carries everything the robot needs."""

from __future__ import annotations

import ast
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
# ... but for the [sim] and [randomize] schemas, which Config reads on the robot, and the
# package's __init__ on the way to them (it imports nothing).
ROBOT_SIDE_IN_SIM = ("sim/config.py", "sim/__init__.py")


def robot_side_modules() -> list[Path]:
    return sorted(
        path for path in PACKAGE.rglob("*.py")
        if path.relative_to(PACKAGE).parts[0] not in WORKSTATION_ONLY
        or path.relative_to(PACKAGE).as_posix() in ROBOT_SIDE_IN_SIM
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
    assert PACKAGE / "sim" / "config.py" in modules
    assert not any("train" in m.parts for m in modules)
    assert [m for m in modules if "sim" in m.parts] == sorted(
        PACKAGE / name for name in ROBOT_SIDE_IN_SIM)
    result = vermin(*modules)
    assert result.returncode == 0, result.stdout + result.stderr


def robot_side_tests() -> list[Path]:
    """The test files scripts/test_python38.sh runs on Python 3.8 (its list is the source)."""
    script = (REPO / "scripts" / "test_python38.sh").read_text()
    block = script.split("robot_tests=(", 1)[1].split(")", 1)[0]
    return [REPO / name for name in block.split()]


def test_robot_side_tests_need_no_python_newer_than_3_8():
    tests = robot_side_tests()
    assert REPO / "tests" / "test_motors.py" in tests and all(t.is_file() for t in tests)
    result = vermin(*tests)
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_3_8_check_catches_what_3_8_lacks(tmp_path):
    source = tmp_path / "newer.py"
    source.write_text("def f(a, b):\n    return list(zip(a, b, strict=True))\n")
    result = vermin(source)
    assert result.returncode != 0
    assert "zip(strict)" in result.stdout


# Subscripted at run time, these need Python 3.9 (PEP 585); in annotations they are strings
# (``from __future__ import annotations``), which vermin checks; vermin does not see them in
# a module-level alias such as ``Handler = Callable[[int], None]``.
PEP585 = {"list", "dict", "tuple", "set", "frozenset", "type", "Callable", "Iterator",
          "Iterable", "Sequence", "Mapping", "MutableMapping", "Generator", "Awaitable"}


def runtime_generics(source: str) -> list[int]:
    """Lines where a PEP 585 generic or an ``X | None`` is evaluated at run time. A module
    that calls ``typing.get_type_hints`` evaluates its classes' field annotations
    (config/sections.py)."""
    tree = ast.parse(source)
    skip: set[int] = set()
    evaluated: set[int] = set()
    if "get_type_hints" in source:
        evaluated = {id(field) for node in ast.walk(tree) if isinstance(node, ast.ClassDef)
                     for field in node.body if isinstance(field, ast.AnnAssign)}
    for node in ast.walk(tree):
        annotations = []
        if id(node) in evaluated:
            continue
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            annotations = [a.annotation for a in (*node.args.args, *node.args.kwonlyargs,
                                                  *node.args.posonlyargs) if a.annotation]
            annotations += [node.returns] if node.returns else []
            annotations += [a.annotation for a in (node.args.vararg, node.args.kwarg)
                            if a is not None and a.annotation]
        elif isinstance(node, ast.AnnAssign):
            annotations = [node.annotation]
        elif isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            annotations = node.body
        for annotation in annotations:
            skip.update(id(n) for n in ast.walk(annotation))
    found = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Subscript):
            name = node.value.attr if isinstance(node.value, ast.Attribute) else getattr(
                node.value, "id", None)
            if name in PEP585:
                found.append(node.lineno)
        elif isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitOr) and any(
            (isinstance(side, ast.Constant) and side.value is None)
            or (isinstance(side, ast.Name) and side.id in {"int", "float", "str", "bool"})
            for side in (node.left, node.right)
        ):
            found.append(node.lineno)
    return sorted(found)


def test_robot_side_evaluates_no_newer_typing_at_run_time():
    offenders = {
        str(path.relative_to(REPO)): lines
        for path in robot_side_modules()
        if (lines := runtime_generics(path.read_text()))
    }
    assert not offenders, f"evaluated at run time, needs Python 3.9+: {offenders}"


def test_the_run_time_typing_check_can_fail():
    source = (
        "from __future__ import annotations\n"
        "from collections.abc import Callable\n"
        "Handler = Callable[[int], None]\n"
        "def f(x: list[int] | None) -> dict[str, int]:\n"
        "    return isinstance(x, int | None)\n"
    )
    assert runtime_generics(source) == [3, 5]
    fields = ("import typing\n"
              "class Section:\n"
              "    a: Optional[List[float]] = None\n"
              "    b: list[float] | None = None\n"
              "hints = typing.get_type_hints(Section)\n")
    assert runtime_generics(fields) == [4, 4]


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
        "jetbot_rt/policies/seek.onnx",
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
