"""``jetbot-train ensemble``: the mean of several policies, checked and written as one."""

from __future__ import annotations

import os
import stat

import numpy as np
import policy_models
import pytest

from jetbot_rt.runtime.policy import OnnxPolicy
from jetbot_rt.train.cli import main
from jetbot_rt.train.ensemble import ENSEMBLE_KEY

CONTRACT = {"jetbot_rt.task": "avoid", "jetbot_rt.max_speed": "0.6",
            "jetbot_rt.deadband_lift": "calibrated"}


def _members(tmp_path, *mus, metadata=CONTRACT):
    return [str(policy_models.constant(tmp_path / f"m{i}.onnx", mu, metadata=metadata))
            for i, mu in enumerate(mus)]


def test_the_ensemble_drives_the_members_mean_and_keeps_their_contract(tmp_path, capsys):
    members = _members(tmp_path, (0.2, 0.4), (0.6, 0.0), (1.0, -0.4))
    out = tmp_path / "ensemble.onnx"
    assert main(["ensemble", *members, "--out", str(out)]) == 0
    assert "the mean of 3 policies" in capsys.readouterr().out
    policy = OnnxPolicy.load(out)
    frame = np.full((56, 56, 3), 90, np.uint8)
    assert np.allclose(policy.infer(frame), [0.6, 0.0], atol=1e-6)
    assert policy.calibrated and policy.max_speed == 0.6
    assert policy.metadata["jetbot_rt.task"] == "avoid"
    folder = tmp_path.name
    assert policy.metadata[ENSEMBLE_KEY] == (f"mean of 3: {folder}/m0.onnx, {folder}/m1.onnx, "
                                             f"{folder}/m2.onnx")


def _refused(capsys, args, *needles):
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("jetbot-train ensemble: error:"), err
    for needle in needles:
        assert needle in err, err


@pytest.mark.parametrize(("key", "value"), [("jetbot_rt.max_speed", "0.5"),
                                            ("jetbot_rt.deadband_lift", None),
                                            ("jetbot_rt.task", "seek")])
def test_members_of_different_contracts_are_refused(tmp_path, capsys, key, value):
    first = _members(tmp_path, (0.2, 0.4))
    other = {**CONTRACT, key: value} if value else {k: v for k, v in CONTRACT.items()
                                                   if k != key}
    second = str(policy_models.constant(tmp_path / "other.onnx", (0.6, 0.0), metadata=other))
    out = tmp_path / "ensemble.onnx"
    _refused(capsys, ["ensemble", *first, second, "--out", str(out)], "other.onnx",
             key.split(".")[1])
    assert not out.exists()


def test_a_different_input_is_refused(tmp_path, capsys):
    first = _members(tmp_path, (0.2, 0.4))
    second = str(policy_models.constant(tmp_path / "big.onnx", size=96, metadata=CONTRACT))
    _refused(capsys, ["ensemble", *first, second, "--out", str(tmp_path / "e.onnx")],
             "big.onnx", "input")


def test_bad_members_and_outputs_are_one_line_errors(tmp_path, capsys):
    members = _members(tmp_path, (0.2, 0.4), (0.6, 0.0))
    _refused(capsys, ["ensemble", members[0], "--out", str(tmp_path / "e.onnx")],
             "two or more")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x08\x01garbage")
    _refused(capsys, ["ensemble", members[0], str(junk), "--out", str(tmp_path / "e.onnx")],
             "junk.onnx", "not a valid ONNX model")
    fifo = tmp_path / "fifo.onnx"
    os.mkfifo(fifo)
    _refused(capsys, ["ensemble", members[0], str(fifo), "--out", str(tmp_path / "e.onnx")],
             "fifo.onnx")
    _refused(capsys, ["ensemble", *members, "--out", str(tmp_path)], "is a directory")
    before = (tmp_path / "m0.onnx").read_bytes()
    _refused(capsys, ["ensemble", *members, "--out", members[0]], "one of the members")
    assert (tmp_path / "m0.onnx").read_bytes() == before


def test_a_link_planted_at_out_is_replaced_not_written_through(tmp_path):
    members = _members(tmp_path, (0.2, 0.4), (0.6, 0.0))
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    out = tmp_path / "ensemble.onnx"
    out.symlink_to(victim)
    assert main(["ensemble", *members, "--out", str(out)]) == 0
    assert victim.read_text() == "keep" and not out.is_symlink()


@pytest.mark.parametrize(("make", "needle"), [
    (lambda p: policy_models.slow(p, 10**15), "holds a subgraph"),  # would never finish
    (policy_models.two_inputs, "one image input"),
    (policy_models.int_output, "not float32"),
])
def test_members_that_are_not_plain_graphs_are_refused_before_running(tmp_path, capsys, make,
                                                                      needle):
    first = _members(tmp_path, (0.2, 0.4), metadata=None)
    other = str(make(tmp_path / "odd.onnx"))
    out = tmp_path / "e.onnx"
    _refused(capsys, ["ensemble", *first, other, "--out", str(out)], "odd.onnx", needle)
    assert not out.exists()


def test_a_member_that_fails_inside_onnxruntime_is_one_line(tmp_path, capsys):
    first = _members(tmp_path, (0.2, 0.4), metadata=None)
    wrong = tmp_path / "wrong.onnx"  # declares [1, 2] actions, returns [1, 3]
    policy_models.constant(wrong, (0.1, 0.2, 0.3), extra_outputs=False)  # type: ignore[arg-type]
    _refused(capsys, ["ensemble", *first, str(wrong), "--out", str(tmp_path / "e.onnx")],
             "cannot build an ensemble")
    assert not (tmp_path / "e.onnx").exists()


def test_an_existing_out_that_is_not_a_file_is_refused_and_left_alone(tmp_path, capsys):
    members = _members(tmp_path, (0.2, 0.4), (0.6, 0.0))
    fifo = tmp_path / "out.onnx"
    os.mkfifo(fifo)
    _refused(capsys, ["ensemble", *members, "--out", str(fifo)], "not a regular file")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_an_ensemble_is_no_start_for_a_fine_tune(tmp_path):
    from jetbot_rt.errors import UsageError
    from jetbot_rt.train.finetune import start_from_onnx

    members = _members(tmp_path, (0.2, 0.4), (0.6, 0.0))
    out = tmp_path / "ensemble.onnx"
    assert main(["ensemble", *members, "--out", str(out)]) == 0
    with pytest.raises(UsageError, match=r"an ensemble .*start from one of its members"):
        start_from_onnx(str(out))


def test_a_video_records_a_tasks_finite_numbers():
    from jetbot_rt.train.video import task_measures

    info = {"distance": np.float32(0.5), "steps_left": np.int64(3), "tick": 1.0,
            "huge": 10**400, "nan": float("nan"), "flag": True, "is_success": np.bool_(True),
            "name": "x", "pose": [0.0, 0.0, 0.0], "sim_time": 0.5}
    assert task_measures(info) == {"distance": 0.5, "steps_left": 3.0, "tick": 1.0}
