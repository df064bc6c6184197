#!/usr/bin/env bash
# The robot side on a real Python 3.8 (the Jetson Nano's JetPack 4.6 runs apt's python3.8):
# a venv with '.[jetson]' from the package index, then the robot-side tests.
# Usage: scripts/test_python38.sh [pytest args]   (PYTHON38=/path/to/python3.8 to choose one)
set -euo pipefail
cd "$(dirname "$0")/.."

py=${PYTHON38:-}
if [[ -z $py ]]; then
    for candidate in python3.8 "$(pyenv root 2>/dev/null)"/versions/3.8*/bin/python3.8; do
        if "$candidate" -c 'import sys; assert sys.version_info[:2] == (3, 8)' 2>/dev/null; then
            py=$candidate
            break
        fi
    done
fi
if [[ -z $py ]]; then
    echo "test_python38: no Python 3.8 found; set PYTHON38 or install one (apt install python3.8 python3.8-venv, or pyenv install 3.8)" >&2
    exit 1
fi

venv=.venv38
[[ -x $venv/bin/python ]] || "$py" -m venv "$venv"
"$venv/bin/python" -m pip install -q --upgrade pip
"$venv/bin/python" -m pip install -q -e '.[jetson]' 'pytest>=7' 'onnx>=1.14'

# Every test of the runtime core and the hardware backends; the sim and trainer tests need
# Python 3.10 (pybullet, torch).
robot_tests=(
    tests/test_actions.py tests/test_config.py tests/test_histogram.py tests/test_i2c.py
    tests/test_pca9685_emulator.py tests/test_motors.py tests/test_service.py
    tests/test_policy.py tests/test_safety.py tests/test_loop.py tests/test_notify.py
    tests/test_check.py tests/test_stop.py tests/test_real_backend_e2e.py
    tests/test_runtime_errors.py tests/test_gst_camera.py tests/test_fault_input.py
    tests/test_byo_policy.py tests/test_monitor.py tests/test_monitor_run.py
    tests/test_console_lines.py tests/test_board_record.py tests/test_teleop.py
    tests/test_drive_page.py
)
"$venv/bin/python" -m pytest -q -p no:cacheprovider "${robot_tests[@]}" "$@"

# The workstation-only commands refuse in one line (exit 2) instead of a traceback.
for command in "jetbot-train --help" "jetbot-rt run --backend sim --duration 1"; do
    set +e
    err=$("$venv/bin/"$command 2>&1 >/dev/null)
    code=$?
    set -e
    if [[ $code != 2 || $(wc -l <<<"$err") != 1 || $err != *"need Python 3.10 or newer"* ]]; then
        echo "test_python38: '$command' on Python 3.8: exit $code, stderr: $err" >&2
        exit 1
    fi
done
echo "test_python38: jetbot-train and --backend sim refuse Python 3.8 in one line (exit 2)"
