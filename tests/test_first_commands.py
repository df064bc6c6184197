"""The first commands a newcomer types: each one works or says in one line what to do."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import pytest
from check_helpers import check, rows, write_config

from jetbot_rt import cli
from jetbot_rt.train.cli import build_parser as train_parser

RUN_CLI = [sys.executable, "-m", "jetbot_rt.cli"]


def test_backend_without_run_is_run(capfd) -> None:
    # `jetbot-rt --backend sim` is `jetbot-rt run --backend sim`: the run's own error shows it
    assert cli.main(["--backend", "sim", "--rate", "0"]) == 2
    (line,) = capfd.readouterr().err.strip().splitlines()
    assert line.startswith("jetbot-rt run: error: --rate: [loop] rate_hz must be"), line


def test_backend_choices_are_listed_and_null_is_gone(capfd) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["run", "--backend", "null"])
    assert exit_info.value.code == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "invalid choice: 'null' (choose from 'real', 'sim')" in err[0]


def help_texts() -> dict[str, str]:
    """Every --help page of both CLIs, as argparse prints it."""
    texts = {}
    parser, modules = cli.build_parser()
    texts["jetbot-rt"] = parser.format_help()
    for name in modules:
        sub_parser, _ = cli.build_parser()
        module = __import__(modules[name], fromlist=["add_arguments"])
        subparsers = next(a for a in sub_parser._actions if a.choices and name in a.choices)
        module.add_arguments(subparsers.choices[name])
        texts[f"jetbot-rt {name}"] = subparsers.choices[name].format_help()
    train = train_parser()
    texts["jetbot-train"] = train.format_help()
    train_subparsers = next(a for a in train._actions if a.choices and "train" in a.choices)
    for name, sub in train_subparsers.choices.items():
        texts[f"jetbot-train {name}"] = sub.format_help()
    return texts


def test_help_pages_have_no_markup_and_show_defaults() -> None:
    texts = help_texts()
    assert {"jetbot-rt run", "jetbot-rt check", "jetbot-train train", "jetbot-train eval"} <= set(
        texts
    )
    for name, text in texts.items():
        assert "``" not in text, f"{name} --help shows reStructuredText"
        assert "(default: None)" not in text, name
    assert "--backend {real,sim}" in texts["jetbot-rt run"]
    assert "camera frames to take (default: 30)" in texts["jetbot-rt check"]
    flat = re.sub(r"\s+", " ", texts["jetbot-train eval"])
    assert "(default: 100)" in flat  # --episodes


def test_run_says_when_it_drives_and_what_the_simulated_robot_did(tmp_path) -> None:
    result = subprocess.run(
        [*RUN_CLI, "run", "--backend", "sim", "--duration", "0.5"],
        capture_output=True, text=True, timeout=120,
        env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run")),
    )
    assert result.returncode == 0, result.stderr  # the sim's watchdog: a hiccup is no fault
    lines = result.stdout.splitlines()
    assert lines[0] == "driving at 30 Hz; Ctrl-C or `jetbot-rt stop` to stop"
    (travelled,) = [line for line in lines if line.strip().startswith("travelled")]
    assert re.fullmatch(r"\s+travelled\s+\d+\.\d\d m; ends \d+\.\d\d m from the goal block",
                        travelled)


def test_sim_without_pybullet_names_the_extra(tmp_path) -> None:
    code = (
        "import sys; sys.modules['pybullet'] = None\n"  # as if it were not installed
        "from jetbot_rt.cli import main\n"
        "sys.exit(main(['run', '--backend', 'sim', '--duration', '1']))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60,
                            env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run")))
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("jetbot-rt run: error: --backend sim: ")
    if sys.version_info[:2] in ((3, 10), (3, 11)):
        assert "pip install -e '.[sim]'" in line
    else:
        assert "uv venv -p 3.11" in line
    assert "driving" not in result.stdout


def test_check_on_a_machine_without_argus_does_not_blame_the_daemon(robot) -> None:
    if subprocess.run(["gst-inspect-1.0", "nvarguscamerasrc"],
                      capture_output=True).returncode == 0:
        pytest.skip("this machine has nvarguscamerasrc")
    result = check(robot, write_config(robot, "csi"))
    camera = rows(result.stdout)["camera"]
    assert "FAIL" in camera
    assert "no nvarguscamerasrc" in camera and "usb:/dev/video0" in camera
    assert "restart nvargus-daemon" not in camera


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="xvfb-run is not installed")
# Mesa's llvmpipe renders on every core, and the run's watchdog is scaled from the GUI step
# time it measures at the start: beside another test (pytest-xdist) later steps took longer
# (seen: "no tick for 0.273 s (timeout 0.255 s)"). Nothing runs beside it, as in a serial run.
@pytest.mark.exclusive
def test_gui_under_a_software_rendered_display_keeps_driving(tmp_path) -> None:
    """Xvfb renders with Mesa on the CPU: a GUI step takes hundreds of ms. The run must not
    end in a watchdog trip after its first tick."""
    result = subprocess.run(
        ["xvfb-run", "-a", *RUN_CLI, "run", "--backend", "sim", "--gui", "--duration", "1"],
        capture_output=True, text=True, timeout=300,
        env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run")),
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert "stopped      duration 1 s reached" in result.stdout  # 12 ticks alone here
    ticks = int(re.search(r"ticks\s+(\d+)", result.stdout).group(1))
    assert ticks >= 2


def test_spin_turns_each_wheel_forward_as_the_runtime_would(robot) -> None:
    """docs/HARDWARE.md: check --spin shows which way each wheel turns; with [actions] sign
    it pulses the direction the runtime calls forward."""
    from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

    chip = PCA9685Emulator(0x60, state_file=robot / "chip.json")
    config = write_config(robot, "gst:videotestsrc is-live=true")
    config.write_text(config.read_text() + "[actions]\nsign = [1, -1]\n")
    result = check(robot, config, "--spin")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "sign [1, -1]" in rows(result.stdout)["spin"]
    chip.refresh()
    # waveshare: left forward on output 1; the right wheel's -1 puts its pulse on output 3
    assert chip.peak_duty[1] > 0 and chip.peak_duty[3] > 0
    assert chip.peak_duty[0] == chip.peak_duty[2] == 0.0
    assert chip.all_off()
