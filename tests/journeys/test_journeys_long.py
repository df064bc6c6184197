"""The documented journeys that take minutes, each from the docs' own commands (read at test
time: doc_commands.py), in a temporary directory, with small step counts where a command has
such a flag. Deselected by default; run them with

    .venv/bin/python -m pytest -q -m long tests/journeys/

(the fresh clone's fresh venv also needs the package index the README's pip command uses)."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from doc_commands import (
    BIN,
    JOURNEYS,
    REPO,
    command,
    environment,
    inline,
    ok,
    python_block,
    sh,
    with_knobs,
)

from jetbot_rt.runtime.policy import bundled_policy_path

pytestmark = pytest.mark.long

needs_xvfb = pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="xvfb-run is missing")


def steps(journey: str) -> list[str]:
    return [command(doc, start) for doc, start in JOURNEYS[journey]]


def test_a_fresh_clone_installs_and_drives_with_the_readmes_first_command(tmp_path: Path):
    """The README's first command verbatim (but 2 s of driving) in a fresh clone of HEAD,
    creating its own venv: no file of this checkout's venv is used."""
    clone = tmp_path / "clone"
    ok(subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], capture_output=True,
                      text=True, timeout=300))
    first = steps("drive the simulator (README)")[0]
    env = environment()
    env["PATH"] = env["PATH"].split(":", 1)[1]  # not this venv's programs
    proc = ok(sh(with_knobs(first, {"--duration 20": "--duration 2"}), clone, timeout=900,
                 env=env))
    assert "driving at 30 Hz" in proc.stdout and "exit code    0" in proc.stdout
    assert (clone / ".venv" / "bin" / "jetbot-rt").exists()


def test_record_report_replay_as_the_readme_says(tmp_path: Path) -> None:
    record, report, replay = steps("record, report, replay (README)")
    shutil.copy(bundled_policy_path(), tmp_path / "new.onnx")  # "another" policy: the same
    ok(sh(with_knobs(record, {"--duration 20": "--duration 3"}), tmp_path))
    reported = ok(sh(report, tmp_path))
    assert (tmp_path / "rec" / "run.mp4").stat().st_size > 0
    assert (tmp_path / "rec" / "run.png").stat().st_size > 0
    assert "stopped      duration 3 s reached (orderly)" in reported.stdout
    replayed = ok(sh(replay, tmp_path))
    assert "|mu - recorded mu|  max 0," in replayed.stdout, "the same weights, the same mu"
    assert not [line for line in replayed.stdout.splitlines() if line.startswith("tick ")]


def test_the_robot_on_the_emulated_board_with_a_second_shell(tmp_path: Path) -> None:
    """docs/HARDWARE.md's harness: the runtime drives the emulated board from one shell; the
    duties are read, `stop` ends it, from another; `check --spin` then pulses each wheel."""
    run, duties, stop, check = steps("the robot on the emulated board (docs/HARDWARE.md)")
    section, key = inline("docs/HARDWARE.md",
                          '[camera] source = "gst:videotestsrc is-live=true"').split(" ", 1)
    (tmp_path / "dry.toml").write_text(f"{section}\n{key}\n")
    knobs = {"/tmp/chip.json": str(tmp_path / "chip.json")}
    assert run.endswith(" &")
    runtime = subprocess.Popen(["bash", "-c", with_knobs(run, {**knobs, " &": ""})],
                               cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=environment())
    try:
        assert runtime.stdout is not None
        first = runtime.stdout.readline()
        assert first.startswith("driving at"), first + runtime.stderr.read()
        time.sleep(0.5)
        driving = ok(sh(with_knobs(duties, knobs), tmp_path)).stdout
        assert any(abs(duty) > 0.05 for duty in json.loads(driving.replace("(", "[").replace(
            ")", "]").replace("'", '"'))), driving
        stopped = ok(sh(with_knobs(stop, knobs), tmp_path))
        out, err = runtime.communicate(timeout=30)
    finally:
        runtime.kill()
    assert runtime.returncode == 0, err
    assert "jetbot-rt stop from pid" in out, out
    assert "EMULATOR" in stopped.stdout
    checked = ok(sh(with_knobs(check, knobs), tmp_path))
    assert "spin" in checked.stdout and "all off" in checked.stdout


def test_train_evaluate_and_compare_with_a_blind_camera_as_the_readme_says(tmp_path: Path):
    """seek by DAgger, two short iterations: the commands work end to end (the figures are
    the documented training's, not this one's)."""
    train, evaluate, blind, video = steps(
        "train, evaluate, compare with a blind camera (README)")
    tiny = "--out runs/seek --iterations 2 --steps-per-iteration 300 --train-samples 512"
    ok(sh(with_knobs(train, {"--out runs/seek": tiny}), tmp_path, timeout=600))
    assert (tmp_path / "runs" / "seek" / "policy.onnx").is_file()
    evaluated = ok(sh(with_knobs(evaluate, {"--episodes 100": "--episodes 2"}), tmp_path))
    assert "success" in evaluated.stdout and "the block pushed less than" in evaluated.stdout
    baseline = ok(sh(with_knobs(blind, {"--episodes 50": "--episodes 2"}), tmp_path))
    assert "(ablate blank)" in baseline.stdout
    ok(sh(with_knobs(video, {"--episodes 3": "--episodes 1"}), tmp_path))
    report = inline("README.md", "jetbot-rt report evals/episode-10000")
    ok(sh(report, tmp_path))
    assert (tmp_path / "evals" / "episode-10000" / "run.png").is_file()


@needs_xvfb
def test_your_own_task_trains_evaluates_and_drives_as_docs_tasks_says(tmp_path: Path):
    train, evaluate, config, drive = steps("your own task (docs/TASKS.md)")
    (tmp_path / "examples").symlink_to(REPO / "examples")
    ok(sh(with_knobs(train, {"--out runs/park": "--out runs/park --timesteps 1024"}),
          tmp_path, timeout=600))
    policy = "--policy runs/park/policy.onnx"
    ok(sh(with_knobs(evaluate, {policy: f"{policy} --episodes 2"}), tmp_path))
    ok(sh(config, tmp_path))
    driven = ok(sh("xvfb-run -a " + with_knobs(drive, {"--gui": "--gui --duration 2"}),
                   tmp_path, timeout=300))
    assert "exit code    0" in driven.stdout


def test_bring_your_own_policy_exports_and_drives(tmp_path: Path) -> None:
    doc = "docs/BRING_YOUR_OWN_POLICY.md"
    (tmp_path / "export.py").write_text(python_block(doc, 'export_policy(model, "my_policy.onnx"'))
    exported = ok(subprocess.run([str(BIN / "python"), "export.py"], cwd=tmp_path,
                                 capture_output=True, text=True, timeout=300))
    assert "my_policy.onnx written" in exported.stdout
    drive = inline(doc, "jetbot-rt run --backend sim --policy my_policy.onnx --duration 10")
    driven = ok(sh(with_knobs(drive, {"--duration 10": "--duration 2"}), tmp_path))
    assert "exit code    0" in driven.stdout


@needs_xvfb
def test_the_gui_without_a_display_runs_under_xvfb_without_pybullets_chatter(tmp_path: Path):
    gui = inline("docs/RUN.md", "xvfb-run -a jetbot-rt run --backend sim --gui --duration 20")
    proc = ok(sh(with_knobs(gui, {"--duration 20": "--duration 2"}), tmp_path, timeout=300))
    assert "driving at 30 Hz" in proc.stdout
    for chatter in ("startThreads", "GL_VENDOR", "b3Printf", "destroy semaphore"):
        assert chatter not in proc.stdout + proc.stderr
