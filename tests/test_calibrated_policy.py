"""A policy trained on a calibrated robot (``[randomize] deadband_lift``) says so in its
metadata (``jetbot_rt.deadband_lift = "calibrated"``), through its checkpoint, its export and
a fine-tune; ``jetbot-rt run`` notes when ``[actions] deadband`` leaves such a policy's robot
unlifted."""

from __future__ import annotations

from pathlib import Path

import policy_models
import pytest
import torch
from runner import run_cli

from jetbot_rt.config.sections import from_dict
from jetbot_rt.errors import UsageError
from jetbot_rt.runtime.policy import OnnxPolicy
from jetbot_rt.train import ppo
from jetbot_rt.train.checkpoint import load_checkpoint
from jetbot_rt.train.env import calibrated_robot
from jetbot_rt.train.evaluate import evaluate
from jetbot_rt.train.export import export_checkpoint
from jetbot_rt.train.finetune import load_start
from jetbot_rt.train.hyperparams import PPOArgs

pytest.importorskip("pybullet")

NOTE = "was trained on a robot whose dead-band is lifted"
LIFTED = {"jetbot_rt.deadband_lift": "calibrated"}


def test_only_a_run_that_randomizes_trains_on_a_calibrated_robot():
    lift = {"deadband_lift": [-0.05, 0.05]}
    assert calibrated_robot(from_dict({"randomize": lift}), "seek")
    assert not calibrated_robot(from_dict({"randomize": lift}), "forward")  # forward: off
    assert not calibrated_robot(from_dict({"randomize": {**lift, "enabled": False}}), "seek")
    assert calibrated_robot(from_dict({"randomize": {**lift, "enabled": True}}), "forward")
    assert not calibrated_robot(from_dict({}), "seek")


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[bool, Path]:
    """A tiny seek run on a calibrated robot (True) and on a plain one (False)."""
    out = {}
    for lift in (True, False):
        out[lift] = tmp_path_factory.mktemp("lifted" if lift else "plain") / "run"
        config = from_dict({"randomize": {"deadband_lift": [-0.05, 0.05]}} if lift else {})
        ppo.train(PPOArgs(task="seek", num_envs=1, num_steps=16, total_timesteps=16,
                          out=str(out[lift]), update_epochs=1, progress=False, workers=0,
                          config=config))
    return out


@pytest.mark.parametrize("lift", [True, False])
def test_the_lift_a_policy_trained_with_reaches_each_export(tmp_path, runs, lift):
    run = runs[lift]
    policy = OnnxPolicy.load(run / "policy.onnx", from_dict({}).policy)
    assert policy.calibrated is lift
    assert load_checkpoint(run / "checkpoint.pt").calibrated is lift
    export_checkpoint(run / "checkpoint.pt", tmp_path / "again.onnx")
    assert OnnxPolicy.load(tmp_path / "again.onnx", from_dict({}).policy).calibrated is lift
    assert load_start(str(run / "policy.onnx")).calibrated is lift
    if lift:  # an evaluation says which robot it measured
        lifted = from_dict({"randomize": {"deadband_lift": [-0.05, 0.05]}})
        report = evaluate(tmp_path / "again.onnx", task="seek", episodes=1, config=lifted)
        assert report["calibrated_policy"] is True and report["deadband_lift"] == [-0.05, 0.05]


def test_a_checkpoint_whose_calibrated_is_not_a_flag_is_refused(tmp_path, runs):
    state = torch.load(runs[True] / "checkpoint.pt", weights_only=True)
    state["calibrated"] = "yes"
    torch.save(state, tmp_path / "bad.pt")
    with pytest.raises(UsageError, match="calibrated must be true or false"):
        load_checkpoint(tmp_path / "bad.pt")


@pytest.mark.parametrize(("metadata", "config", "noted"), [
    (LIFTED, "[sim]\ndeadband = 0.1\n", True),  # a dead-band the runtime does not lift
    (LIFTED, "[sim]\ndeadband = 0.1\n[actions]\ndeadband = 0.1\n", False),
    (LIFTED, "", False),  # the simulated robot has no dead-band: nothing to lift
    (LIFTED, "[randomize]\nenabled = true\n", True),  # a drawn one
    ({}, "[sim]\ndeadband = 0.1\n", False),
])
def test_run_notes_a_calibrated_policy_on_an_unlifted_robot(tmp_path, metadata, config, noted):
    policy = policy_models.constant(tmp_path / "p.onnx", (0.5, 0.5), metadata=metadata)
    (tmp_path / "c.toml").write_text("[loop]\nwatchdog_timeout = 1.0\n" + config)
    result = run_cli(["run", "--backend", "sim", "--policy", str(policy), "--config",
                      str(tmp_path / "c.toml"), "--duration", "0.3"],
                     telemetry=tmp_path / "t.jsonl")
    assert result.returncode == 0, result.stderr
    assert (NOTE in result.stderr) is noted, result.stderr
