"""Can the robot install ``jetbot_rt[jetson]`` from wheels alone? Asks PyPI, as pip on the
robot would, for each JetPack: a dry-run resolution with ``--only-binary=:all:``, the robot's
platform tags (aarch64, manylinux no newer than its glibc) and its CPython version.

pip evaluates environment markers (``python_version < '3.11'``) with the interpreter that runs
it, not with ``--python-version``, so each resolution runs under a Python of the robot's minor
version (found on PATH, in pyenv, or named by PYTHON38 / PYTHON310).

    python scripts/check_robot_wheels.py        # exit 0: both resolve; 1: a failure, said why

Needs https://pypi.org; without it the script says so and exits 1.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile
import urllib.request
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
INDEX = "https://pypi.org/simple"


@dataclass
class Target:
    name: str
    python: str  # CPython minor version of the robot's Python
    glibc: int  # 2.<glibc> on the robot
    # package -> (predicate on the resolved version, what it means)
    expect: dict


def _major(version: str) -> int:
    return int(version.split(".")[0])


TARGETS = [
    Target("JetPack 4.6 (Jetson Nano; Ubuntu 18.04, apt's python3.8, glibc 2.27)", "3.8", 27, {
        "onnxruntime": (lambda v: v.startswith("1.19."), "the last onnxruntime with cp38 wheels"),
    }),
    Target("JetPack 6 (Orin; Ubuntu 22.04, Python 3.10, glibc 2.35)", "3.10", 35, {
        "numpy": (lambda v: _major(v) < 2,
                  "numpy 1.x: NVIDIA's onnxruntime-gpu for JetPack 6 is built against numpy 1"),
    }),
]


def fail(message: str) -> None:
    print(f"check_robot_wheels: {message}", file=sys.stderr)
    sys.exit(1)


def interpreter(version: str) -> str:
    env = os.environ.get("PYTHON" + version.replace(".", ""))
    candidates = [env] if env else []
    candidates += [f"python{version}"]
    pyenv = shutil.which("pyenv")
    if pyenv:
        root = subprocess.run([pyenv, "root"], capture_output=True, text=True).stdout.strip()
        candidates += sorted(glob.glob(f"{root}/versions/{version}.*/bin/python{version}"))
    for candidate in candidates:
        probe = subprocess.run(
            [candidate, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"],
            capture_output=True, text=True,
        ) if shutil.which(candidate) or os.path.isfile(candidate) else None
        if probe and probe.returncode == 0 and probe.stdout.strip() == version:
            return candidate
    fail(f"no Python {version} found to evaluate the robot's environment markers; set "
         f"PYTHON{version.replace('.', '')} or install one (pyenv install {version})")
    raise AssertionError  # unreachable


def check_online() -> None:
    try:
        urllib.request.urlopen(f"{INDEX}/pip/", timeout=15).close()
    except OSError as exc:
        fail(f"PyPI ({INDEX}) is not reachable ({exc}); this check needs the network")


def resolve(target: Target, work: Path) -> dict[str, str]:
    platforms = [f"manylinux_2_{minor}_aarch64" for minor in range(target.glibc, 16, -1)]
    platforms += ["manylinux2014_aarch64"]
    report = work / f"report-{target.python}.json"
    command = [
        interpreter(target.python), "-m", "pip", "--isolated", "--disable-pip-version-check",
        "install", "--dry-run", "--ignore-installed", "--quiet",
        "--target", str(work / "target"), "--report", str(report),
        "--only-binary=:all:", "--implementation", "cp", "--python-version", target.python,
        *[arg for p in platforms for arg in ("--platform", p)],
        "--index-url", INDEX,
    ]
    cert = os.environ.get("PIP_CERT")
    if cert:
        command += ["--cert", cert]
    result = subprocess.run([*command, f"{REPO}[jetson]"], capture_output=True, text=True)
    if result.returncode != 0:
        fail(f"{target.name}: pip cannot resolve '.[jetson]' from wheels:\n{result.stderr}")
    installs = json.loads(report.read_text())["install"]
    return {i["metadata"]["name"].lower(): i["metadata"]["version"] for i in installs}


def main() -> int:
    check_online()
    with tempfile.TemporaryDirectory() as tmp:
        for target in TARGETS:
            versions = resolve(target, Path(tmp))
            shown = ", ".join(
                f"{name} {versions[name]}"
                for name in ("numpy", "onnxruntime", "opencv-python-headless", "smbus2",
                             "adafruit-circuitpython-motorkit")
                if name in versions
            )
            print(f"{target.name}: {len(versions)} wheels; {shown}")
            for name, (ok, meaning) in target.expect.items():
                if name not in versions or not ok(versions[name]):
                    fail(f"{target.name}: got {name} {versions.get(name)}; expected {meaning}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
