"""The documented journeys that take minutes, each from the docs' own commands (read at test
time: doc_commands.py), in a temporary directory, with small step counts where a command has
such a flag. Deselected by default; run them with

    .venv/bin/python -m pytest -q -m long tests/journeys/

(the fresh clone's fresh venv also needs the package index the README's pip command uses)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
import urllib.request
from pathlib import Path

import onnxruntime
import pytest
import tomllib
from doc_commands import (
    BIN,
    INLINE,
    JOURNEYS,
    REPO,
    TOML_BLOCKS,
    command,
    environment,
    inline,
    ok,
    python_block,
    sh,
    toml_block,
    with_knobs,
)

from jetbot_rt.runtime.policy import bundled_policy_path

pytestmark = pytest.mark.long

needs_xvfb = pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="xvfb-run is missing")
needs_gst = pytest.mark.skipif(shutil.which("gst-launch-1.0") is None,
                               reason="gst-launch-1.0 is missing (the videotestsrc camera)")


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


def texts(journey: str) -> list[str]:
    """The journey's TOML blocks, then its running-text commands and settings, as the docs
    have them now."""
    return ([toml_block(doc, containing) for doc, containing in TOML_BLOCKS.get(journey, [])]
            + [inline(doc, text) for doc, text in INLINE.get(journey, [])])


def printed_toml(stdout: str, first: str) -> dict:
    """The TOML a command printed, from its line starting with ``first`` on."""
    start = stdout.index(first)
    return tomllib.loads(stdout[start:])


def test_calibrate_in_the_sim_gives_the_docs_own_example_back_within_its_tolerances(
        tmp_path: Path) -> None:
    """docs/CALIBRATION.md's proof in the simulator, verbatim. The doc shows no TRUTH.toml of
    its own; its example output (the [sim] and [randomize] tables the command writes, a config
    the simulator reads) is the truth: driven, recorded and fitted back, within the stated
    tolerances, printed as the doc shows it (each value's +- comment, the [randomize] ranges
    centred on what was measured)."""
    (calibrate,) = steps("calibrate the drive in the simulator (docs/CALIBRATION.md)")
    (example,) = texts("calibrate the drive in the simulator (docs/CALIBRATION.md)")
    (tmp_path / "TRUTH.toml").write_text(example)
    truth = tomllib.loads(example)["sim"]
    proc = ok(sh(calibrate, tmp_path))
    assert re.search(r"^# jetbot-rt calibrate: fitted from \S*calibration-\d", proc.stdout,
                     re.M), proc.stdout
    printed = proc.stdout[proc.stdout.index("# jetbot-rt calibrate: fitted from"):]
    for key in ("motor_gain", "wheel_gain", "deadband", "latency", "motor_tau"):
        assert re.search(rf"^{key} = \S.*  # \+- ", printed, re.M), (key, printed)
    fitted = tomllib.loads(printed)
    sim, randomize = fitted["sim"], fitted["randomize"]
    assert abs(sim["motor_gain"] / truth["motor_gain"] - 1) < 0.08, sim
    assert all(abs(got - want) < 0.04 for got, want in zip(sim["wheel_gain"],
                                                           truth["wheel_gain"])), sim
    assert min(sim["wheel_gain"]) < 1 == max(sim["wheel_gain"]), "the weak wheel below 1"
    assert abs(sim["deadband"] - truth["deadband"]) < 0.02, sim
    assert abs(sim["latency"] - truth["latency"] - truth["camera_latency"]) < 0.015, sim
    assert sim["camera_latency"] == 0.0
    assert randomize["deadband"] == pytest.approx(
        [sim["deadband"] - 0.05, sim["deadband"] + 0.05], abs=1e-3)
    assert randomize["latency"] == pytest.approx(
        [sim["latency"] - 0.03, sim["latency"] + 0.05], abs=1e-3)
    assert randomize["camera_latency"] == [0.0, 0.0]
    recordings = list(tmp_path.glob("calibration-*"))
    assert len(recordings) == 1 and (recordings[0] / "ticks.jsonl").is_file()


def test_calibrate_the_lens_in_the_sim_gives_the_docs_own_lens_back_within_its_tolerances(
        tmp_path: Path) -> None:
    """docs/CALIBRATION.md's lens proof in the simulator, verbatim, with the doc's example
    output (the datasheet lens as fitted) as TRUTH.toml: the board's views are saved, and the
    [sim] lens keys printed as the doc shows them, within its stated tolerances (focal 1.5 %,
    centre 0.01 of the frame, k1 0.03)."""
    (calibrate,) = steps("calibrate the lens in the simulator (docs/CALIBRATION.md)")
    (example,) = texts("calibrate the lens in the simulator (docs/CALIBRATION.md)")
    (tmp_path / "TRUTH.toml").write_text(example)
    truth = tomllib.loads(example)["sim"]
    proc = ok(sh(calibrate, tmp_path))
    saved = re.search(r"saved the views in (\S+) \(--camera --frames \1 fits them again\)",
                      proc.stdout)
    assert saved and list((tmp_path / saved.group(1)).glob("view-*.png")), proc.stdout
    assert re.search(rf"^# jetbot-rt calibrate --camera: \d+ views of the board in "
                     rf"{re.escape(saved.group(1))}, 640x360$", proc.stdout, re.M), proc.stdout
    assert re.search(r"^# reprojection rms \d+\.\d+ px", proc.stdout, re.M)
    lens = printed_toml(proc.stdout, "# jetbot-rt calibrate --camera:")["sim"]
    assert lens["lens"] == "fisheye"
    assert abs(lens["lens_focal"] / truth["lens_focal"] - 1) < 0.015, lens
    assert all(abs(got - want) < 0.01 for got, want in zip(lens["lens_center"],
                                                           truth["lens_center"])), lens
    assert abs(lens["lens_k1"] - truth["lens_k1"]) < 0.03, lens
    assert {"lens_k2", "lens_k3", "lens_k4"} <= lens.keys()


def test_drive_take_over_fine_tune_and_evaluate_in_the_sim_as_docs_drive_says(
        tmp_path: Path) -> None:
    """docs/DRIVE.md's proof, its main commands, short: the scripted person takes over from the
    bundled seek policy (drives 1 and 3) and drives by hand (4-6) in the hidden world, each
    drive its own seed as the doc's comment says (``world_N.toml``, ``takeover_N``,
    ``hand_N``: the doc's N), then the fine-tune (20 steps, 128 simulator frames) and 2
    held-out episodes of the fine-tuned policy. Checked: each recording says who drove each
    tick, the takeovers are in the takeover drives, the ONNX keeps the runtime's contract, the
    eval prints one JSON object."""
    journey = "drive, take over, fine-tune, evaluate in the simulator (docs/DRIVE.md)"
    takeover, hand, finetune, evaluate = steps(journey)
    texts(journey)  # the seeds and the world files, as the doc says them
    (tmp_path / "jetbot_rt").symlink_to(REPO / "jetbot_rt")  # the doc's paths: the checkout's
    (tmp_path / "benchmarks").symlink_to(REPO / "benchmarks")
    hidden = (REPO / "benchmarks" / "drive" / "hidden_world.toml").read_text()
    assert "\n[sim]\n" in hidden
    drives = [(1, takeover, "--duration 200", "takeover"), (3, takeover, "--duration 200",
                                                             "takeover")]
    drives += [(n, hand, "--duration 110", "hand") for n in (4, 5, 6)]
    for n, drive, duration, name in drives:
        (tmp_path / f"world_{n}.toml").write_text(hidden.replace("\n[sim]\n",
                                                                 f"\n[sim]\nseed = {n}\n", 1))
        first = 1 if name == "takeover" else 4
        knobs = {f"world_{first}.toml": f"world_{n}.toml",
                 f"--record {name}_{first}": f"--record {name}_{n}",
                 duration: "--duration 8" if name == "takeover" else "--duration 3"}
        driven = ok(sh(with_knobs(drive, knobs), tmp_path)).stdout
        said = re.search(r"^drive: (\d+) ticks, (\d+) by hand \(\d+%\)(, (\d+) takeovers)?",
                         driven, re.M)
        assert said, driven
        record = tmp_path / f"{name}_{n}"
        meta = json.loads((record / "meta.json").read_text())
        assert meta["source"] == "jetbot-rt drive" and meta["drive"]["input"] == "scripted"
        assert meta["drive"]["policy_drives"] is (name == "takeover")
        ticks = [json.loads(line) for line in (record / "ticks.jsonl").read_text().splitlines()]
        drivers = [t["driver"] for t in ticks if "event" not in t]
        assert drivers and int(said.group(1)) > 0
        if name == "hand":
            assert set(drivers) == {"human"} and said.group(3) is None
            assert said.group(1) == said.group(2), driven
        else:
            assert int(said.group(4)) >= 1, f"no takeover in 8 s: {driven}"
            assert any(t.get("event") == "takeover" for t in ticks)
            assert {"policy", "human"} <= set(drivers)
        assert (record / meta["frames"]).stat().st_size > 0
    tuned = ok(sh(with_knobs(finetune, {"--out ft_mix": "--out ft_mix --steps 20 "
                                                       "--sim-frames 128"}),
                  tmp_path, timeout=300)).stdout
    assert re.search(r"fine-tuned on \d+ human ticks \(\d+ takeovers\) and 128 sim frames in "
                     r"\d+ s; action error on the human ticks \d\.\d+ -> \d\.\d+, held out "
                     r"\d\.\d+ -> \d\.\d+; policy \S*ft_mix/policy\.onnx", tuned), tuned
    summary = json.loads((tmp_path / "ft_mix" / "finetune.json").read_text())
    assert summary["steps"] == 20 and summary["takeovers"] >= 1
    session = onnxruntime.InferenceSession(str(tmp_path / "ft_mix" / "policy.onnx"))
    assert session.get_modelmeta().custom_metadata_map["jetbot_rt.task"] == "seek"
    evaluated = ok(sh(with_knobs(evaluate, {"--episodes 100": "--episodes 2"}), tmp_path,
                      timeout=300))
    result = json.loads(evaluated.stdout)
    assert result["episodes"] == 2 and result["task"] == "seek" and result["seed"] == 10000
    assert result["policy"].endswith("ft_mix/policy.onnx") and 0 <= result["success_rate"] <= 1


def _get(url: str) -> tuple[int, str, bytes]:
    with urllib.request.urlopen(url, timeout=10) as response:
        return response.status, response.headers["Content-Type"], response.read()


@needs_gst
def test_watch_the_policy_on_the_emulated_boards_live_page_then_stop_it_from_there(
        tmp_path: Path) -> None:
    """docs/REAL_DATA.md's "test before driving": the policy on the real backend with the
    emulated board and HARDWARE.md's videotestsrc camera for the robot's, watched on the live
    page (docs/MONITOR.md): the page, /state and the MJPEG stream over HTTP while it runs,
    then the page's STOP: exit 0, the doc's stop line, every duty at zero. Knobs: the robot's
    fixed paths (its installed program, /opt/jetbot-rt, run here as this checkout's
    ``jetbot-rt`` without sudo, which the emulated board and a loopback port do not need; its
    config and the chip's file) for temporary ones, and port 0 (any free one) for 8080."""
    journey = "watch the policy on the emulated board's live page (docs/REAL_DATA.md)"
    run, duties = steps(journey)
    policy_line, camera_line, _ = texts(journey)
    policy_section, policy_key = policy_line.split("`")[1].split(" ", 1)
    shutil.copy(bundled_policy_path("seek"), tmp_path / "policy.onnx")  # REAL_DATA.md step 1
    camera_section, camera_key = camera_line.split(" ", 1)
    (tmp_path / "config.toml").write_text("\n".join([
        camera_section, camera_key,
        policy_section, policy_key.replace("/etc/jetbot-rt/policy.onnx",
                                           str(tmp_path / "policy.onnx")), ""]))
    knobs = {"sudo /opt/jetbot-rt/bin/jetbot-rt": "jetbot-rt",
             "/etc/jetbot-rt/config.toml": str(tmp_path / "config.toml"),
             "/tmp/chip.json": str(tmp_path / "chip.json"), "--monitor 8080": "--monitor 0"}
    runtime = subprocess.Popen(["bash", "-c", with_knobs(run, knobs)], cwd=tmp_path,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=environment())
    try:
        assert runtime.stdout is not None
        lines: list[str] = []  # the monitor's URL, `driving at`, then the emulator's notice
        while len(lines) < 10 and not (lines and "PCA9685 EMULATOR" in lines[-1]):
            lines.append(runtime.stdout.readline())
        assert "PCA9685 EMULATOR" in lines[-1], [*lines, runtime.stderr.read()]
        assert any(line.startswith("driving at") for line in lines), lines
        url = next(m.group(1) for m in map(re.compile(r"monitor: (http://127\.0\.0\.1:\d+/) ")
                                           .match, lines) if m)
        status, kind, page = _get(url)
        assert status == 200 and kind.startswith("text/html") and b"monitor.js" in page
        deadline = time.monotonic() + 30
        state = json.loads(_get(url + "state")[2])
        while state["ticks"] < 30 and time.monotonic() < deadline:
            time.sleep(0.2)
            state = json.loads(_get(url + "state")[2])
        assert state["state"] == "driving" and state["ticks"] >= 30, state
        assert len(state["record"]["mu"]) == 2 and "ended" not in state
        with urllib.request.urlopen(url + "stream.mjpg?view=prepared", timeout=10) as stream:
            assert stream.headers["Content-Type"].startswith("multipart/x-mixed-replace")
            data = b""
            while b"\xff\xd8" not in data and len(data) < 1 << 20:
                data += stream.read(256)
            assert b"Content-Type: image/jpeg" in data and b"\xff\xd8" in data
        stop = urllib.request.Request(url + "stop", data=b"", method="POST")
        with urllib.request.urlopen(stop, timeout=10) as stopping:
            assert stopping.status == 200
        out, err = runtime.communicate(timeout=30)
    finally:
        runtime.kill()
    assert runtime.returncode == 0, (out, err)
    assert re.search(r"^\s*stopped\s+stop from the monitor page \(127\.0\.0\.1\)", out, re.M), out
    off = ok(sh(with_knobs(duties, {"/tmp/chip.json": str(tmp_path / "chip.json")}), tmp_path))
    duties_after = json.loads(off.stdout.replace("(", "[").replace(")", "]"))
    assert duties_after and all(duty == 0 for duty in duties_after), off.stdout
