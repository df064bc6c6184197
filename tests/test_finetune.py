"""``jetbot-train finetune``: the person's ticks of a drive recording as labels, the starting
network read from the bundled policy's own ONNX, the runtime's contract on the way out; and
recordings or starting files that are not what they claim, refused in one line."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from policy_models import constant

from jetbot_rt.errors import UsageError
from jetbot_rt.recording.recorder import Recorder
from jetbot_rt.runtime.loop import TickResult
from jetbot_rt.runtime.policy import OnnxPolicy, bundled_policy_path

pytest.importorskip("torch")

from jetbot_rt.train.finetune import FinetuneArgs, finetune, read_labels

SEEK = str(bundled_policy_path("seek"))
RATE_HZ = 30.0


def drive_recording(path: Path, ticks: int = 24, size: int = 56) -> Path:
    """What ``jetbot-rt drive --policy`` writes, through the real recorder: the policy drives
    the even ticks, the person the odd ones; the person steers left on bright frames and
    right on dark ones, which the policy does not."""
    recorder = Recorder(path, {"source": "jetbot-rt drive", "backend": "sim"}, (size, size),
                        RATE_HZ, t0=0.0, clock=lambda: ticks / RATE_HZ)
    rng = np.random.default_rng(1)
    for tick in range(1, ticks + 1):
        bright = tick % 4 == 1
        image = np.full((size, size, 3), 220 if bright else 30, np.uint8)
        image += rng.integers(0, 10, image.shape, dtype=np.uint8)
        human = tick % 2 == 1
        extra = {
            "driver": "human" if human else "policy",
            "human": ([-0.5, 0.5] if bright else [0.5, -0.5]) if human else None,
            "policy_mu": [0.9, 0.9]}
        recorder.observe(TickResult(
            tick=tick, t_start=tick / RATE_HZ, deadline=tick / RATE_HZ, image=image,
            frame_index=tick, frame_age_ms=0.0, mu=[0.9, 0.9], cmd=(0.45, 0.45), infer_ms=1.0,
            tick_ms=2.0, write_ms=0.1, advance_ms=None, overruns=0, extra=extra))
        if human and tick == 1:
            recorder.event("takeover", driver="human", tick=tick)
    recorder.close({"reason": "test", "exit_code": 0}, timeout=None)
    return path


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> Path:
    """One drive recording for the module (the writer process takes a second to start)."""
    return drive_recording(tmp_path_factory.mktemp("made") / "rec")


@pytest.fixture
def rec(made, tmp_path) -> Path:
    """A copy of it, this test's to spoil."""
    return Path(shutil.copytree(made, tmp_path / "rec"))


def test_the_human_ticks_with_a_command_are_the_labels(rec):
    labels = read_labels([str(rec)], 56)
    assert (labels.ticks, len(labels.labels), labels.takeovers) == (24, 12, 1)
    bright = labels.frames.mean(axis=(1, 2, 3)) > 128
    assert bright.any() and not bright.all()
    assert np.array_equal(labels.labels[bright], np.tile([-0.5, 0.5], (bright.sum(), 1)))
    assert np.array_equal(labels.labels[~bright], np.tile([0.5, -0.5], ((~bright).sum(), 1)))


def test_a_label_delay_pairs_each_frame_with_the_command_given_that_many_ticks_later(rec):
    lines = [json.loads(line) for line in (rec / "ticks.jsonl").read_text().splitlines()]
    for record in lines:
        if "tick" in record:
            record.update(driver="human", human=[record["tick"] / 100, 0.0])
        if record.get("tick") == 10:
            record.update(driver="policy")  # handed back: no label reaches across it
    (rec / "ticks.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    labels = read_labels([str(rec)], 56, label_delay=2)
    # the frames of ticks 1-7 and 11-22, labelled with the commands of ticks 3-9 and 13-24
    later = [t / 100 for t in [*range(3, 10), *range(13, 25)]]
    assert labels.labels[:, 0].tolist() == pytest.approx(later)


def test_the_bundled_onnx_is_read_into_the_trainers_network_with_its_own_outputs():
    from jetbot_rt.train.finetune import start_from_onnx

    start = start_from_onnx(SEEK)
    assert start.task == "seek" and start.max_speed == 0.5
    assert start.model.config.image_size == 56


@pytest.mark.long
def test_a_small_finetune_learns_the_persons_commands_and_keeps_the_runtime_contract(
        rec, tmp_path):
    summary = finetune(FinetuneArgs([str(rec)], SEEK, str(tmp_path / "out"), steps=25,
                                    batch_size=8, learning_rate=1e-3, sim_share=0.0, label_delay=0,
                                    torch_threads=1,
                                    holdout=(str(rec),)))
    assert summary["human_ticks"] == 12 and summary["ticks_read"] == 24
    assert summary["takeovers"] == 1 and summary["task"] == "seek"
    before, after = summary["action_error_before"], summary["action_error_after"]
    assert after["train"] < before["train"] / 2 and after["holdout"] == after["train"]
    policy = OnnxPolicy.load(tmp_path / "out" / "policy.onnx")
    assert policy.metadata["jetbot_rt.task"] == "seek" and policy.max_speed == 0.5
    bright = np.full((56, 56, 3), 220, np.uint8)
    assert policy.infer(bright)[0] < policy.infer(bright)[1]  # steers left, as taught
    saved = json.loads((tmp_path / "out" / "finetune.json").read_text())
    assert saved["human_ticks"] == 12


@pytest.mark.long
def test_the_simulators_share_is_collected_and_mixed_in(rec, tmp_path):
    summary = finetune(FinetuneArgs([str(rec)], SEEK, str(tmp_path / "out"), steps=20,
                                    batch_size=8, sim_frames=120, label_delay=0))
    assert summary["sim_frames"] == 120 and summary["sim_share"] == 0.7


def test_an_old_recording_still_reads_and_has_no_labels(rec):
    """Version 1: no drive keys in the ticks."""
    meta = json.loads((rec / "meta.json").read_text())
    (rec / "meta.json").write_text(json.dumps({**meta, "version": 1}))
    lines = [json.loads(line) for line in (rec / "ticks.jsonl").read_text().splitlines()]
    for record in lines:
        for key in ("driver", "human", "policy_mu"):
            record.pop(key, None)
    (rec / "ticks.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    with pytest.raises(UsageError, match="no human ticks with a command"):
        read_labels([str(rec)], 56)


def spoil_ticks(rec: Path) -> None:
    lines = (rec / "ticks.jsonl").read_text().splitlines()
    record = json.loads(lines[0])
    record["human"] = [2.0, 0.0]
    (rec / "ticks.jsonl").write_text("\n".join([json.dumps(record), *lines[1:]]) + "\n")


def link_ticks(rec: Path) -> None:
    os.replace(rec / "ticks.jsonl", rec.parent / "elsewhere.jsonl")
    os.symlink(rec.parent / "elsewhere.jsonl", rec / "ticks.jsonl")


@pytest.mark.parametrize(("spoil", "line"), [
    (spoil_ticks, "line 1: human[0] must be within [-1, 1]"),
    (link_ticks, "ticks.jsonl"),
    (lambda rec: (rec / "meta.json").write_text('{"format": 1}'), "recording format"),
])
def test_a_hostile_recording_is_refused_in_one_line(rec, spoil, line):
    spoil(rec)
    with pytest.raises(UsageError, match=line.replace("[", r"\[").replace("]", r"\]")):
        read_labels([str(rec)], 56)


READ_FRAMES = """import sys
from jetbot_rt.train.decoder_log import quiet_ffmpeg
quiet_ffmpeg()
from jetbot_rt.recording.reader import Recording
print(sum(1 for _ in Recording.open(sys.argv[1]).frames()))
"""


def test_a_truncated_video_reads_to_its_last_whole_frame_without_ffmpegs_own_log_line(rec):
    """In a fresh process (FFmpeg's level is set at a process's first capture), reading as
    read_labels does: FFmpeg's "File ended prematurely" must not join our one-line error."""
    frames = rec / "frames.mkv"
    data = frames.read_bytes()
    frames.write_bytes(data[:len(data) // 2])
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_FFMPEG")}
    result = subprocess.run([sys.executable, "-c", READ_FRAMES, str(rec)], env=env,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stderr == "", result.stderr
    assert 0 < int(result.stdout) < 24


def test_frames_of_another_size_than_the_network_are_refused(rec):
    meta = json.loads((rec / "meta.json").read_text())
    (rec / "meta.json").write_text(json.dumps({**meta, "frame_size": [32, 32]}))
    with pytest.raises(UsageError, match="frames of 32x32, the network takes 56x56"):
        read_labels([str(rec)], 56)


def test_a_starting_onnx_that_is_not_ours_is_refused_before_any_work(rec, tmp_path):
    other = constant(tmp_path / "constant.onnx", size=56)
    with pytest.raises(UsageError, match=r"--init .*constant\.onnx: its weights are not those"):
        finetune(FinetuneArgs([str(rec)], str(other), str(tmp_path / "out"), sim_share=0.0))
    assert not (tmp_path / "out" / "policy.onnx").exists()


def test_a_starting_file_that_names_code_as_its_task_is_refused(rec, tmp_path):
    from policy_models import constant as named

    other = named(tmp_path / "code.onnx", size=56,
                  metadata={"jetbot_rt.task": "/tmp/evil.py:Task"})
    with pytest.raises(UsageError, match="code in a file or module"):
        from jetbot_rt.train.finetune import file_task

        file_task(OnnxPolicy.load(other).metadata["jetbot_rt.task"], str(other))
