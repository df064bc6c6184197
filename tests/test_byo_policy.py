"""A policy trained elsewhere (docs/BRING_YOUR_OWN_POLICY.md): the reference rl_games network,
exported as its export_onnx.py did (input ``obs`` NHWC float32, outputs ``mu``, ``log_std``,
``value``, opset 16, no metadata), driven with the [policy] keys that state its training."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from check_helpers import check, rows, write_config
from onnx import TensorProto, helper, numpy_helper
from policy_models import rl_games_actor_critic

from jetbot_rt.config.sections import PolicyConfig, load_config
from jetbot_rt.errors import UsageError
from jetbot_rt.runtime.policy import OnnxPolicy

SIZE = 64  # the reference's is 224 (19 M parameters); the same layers at 64x64 keep the test small


def camera_frame(seed: int = 1) -> np.ndarray:
    """An RGB frame with every value from 0 to 255 and unequal channels."""
    return np.random.default_rng(seed).integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)


def reference_mu(model: Path, obs: np.ndarray) -> np.ndarray:
    """What the network gives for the observation as training built it."""
    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    (mu,) = session.run(["mu"], {"obs": obs[None].astype(np.float32)})
    return mu.reshape(-1)


def test_without_metadata_the_defaults_are_the_isaac_lab_ones(tmp_path) -> None:
    policy = OnnxPolicy.load(rl_games_actor_critic(tmp_path / "seed.onnx", SIZE))
    described = policy.describe()
    assert {key: described[key] for key in ("input", "layout", "dtype", "color_order",
                                            "pixel_range", "clip", "action_output")} == {
        "input": "obs", "layout": "NHWC", "dtype": "float32", "color_order": "RGB",
        "pixel_range": "0-255", "clip": None, "action_output": "mu"}
    frame = camera_frame()
    np.testing.assert_allclose(policy.infer(frame), reference_mu(policy.path, frame), rtol=1e-5)


def test_clip_and_colour_order_reproduce_the_training_input(tmp_path) -> None:
    """rl_games' clip_observations 5.0 clipped the 0..255 pixels to 0..5 in training; a
    network trained on BGR frames gets BGR."""
    model = rl_games_actor_critic(tmp_path / "seed.onnx", SIZE)
    config_file = tmp_path / "byo.toml"
    config_file.write_text('[policy]\nclip = 5.0\ncolor_order = "BGR"\n')
    policy = OnnxPolicy.load(model, load_config(config_file).policy)
    frame = camera_frame()
    trained_on = np.clip(frame[:, :, ::-1].astype(np.float32), -5.0, 5.0)
    mu = policy.infer(frame)
    np.testing.assert_allclose(mu, reference_mu(model, trained_on), rtol=1e-5, atol=1e-6)
    unclipped = reference_mu(model, frame[:, :, ::-1].astype(np.float32))
    assert not np.allclose(mu, unclipped, rtol=1e-3)  # the clip changes what the net sees


def uint8_policy(path: Path) -> Path:
    graph = helper.make_graph(
        [helper.make_node("Cast", ["obs"], ["f"], to=TensorProto.FLOAT),
         helper.make_node("ReduceMean", ["f"], ["m"], keepdims=0),
         helper.make_node("Add", ["zero", "m"], ["mu"])],
        "uint8_input",
        [helper.make_tensor_value_info("obs", TensorProto.UINT8, [1, SIZE, SIZE, 3])],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])],
        [numpy_helper.from_array(np.zeros((1, 2), np.float32), "zero")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 16)])
    model.ir_version = 8  # what onnxruntime 1.19 (the last for Python 3.8) reads
    onnx.save(model, path)
    return path


def test_clip_is_refused_for_a_uint8_input_and_must_be_positive(tmp_path) -> None:
    uint8_model = uint8_policy(tmp_path / "u8.onnx")
    OnnxPolicy.load(uint8_model)  # fine without clip
    with pytest.raises(UsageError, match="clip needs a float input"):
        OnnxPolicy.load(uint8_model, PolicyConfig(clip=5.0))
    bad = tmp_path / "bad.toml"
    bad.write_text("[policy]\nclip = 0\n")
    with pytest.raises(UsageError, match=r"\[policy\] clip must be a number in \[0.001, 1e\+06\]"):
        load_config(bad)


def test_check_shows_how_the_model_is_fed(robot, tmp_path) -> None:
    model = rl_games_actor_critic(robot / "policy.onnx", SIZE)
    config = write_config(robot, "gst:videotestsrc is-live=true")
    config.write_text(config.read_text() + "[policy]\nclip = 5.0\n")
    result = check(robot, config)
    assert f"input obs NHWC {SIZE}x{SIZE} float32 RGB 0-255 clip 5; action output mu" in rows(
        result.stdout)["policy"], result.stdout
    assert str(model) in rows(result.stdout)["policy"]
