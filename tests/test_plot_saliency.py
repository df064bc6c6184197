"""benchmarks/plot_saliency.py's occlusion map, on tiny ONNX policies run by onnxruntime."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np
import onnx
import policy_models
from onnx import TensorProto, helper, numpy_helper
from script_module import load_script

from jetbot_rt.runtime.policy import OnnxPolicy

SIZE = 56


def _saliency() -> ModuleType:
    return load_script("benchmarks/plot_saliency.py")


def _region_reader(path: Path, rows: tuple[int, int], cols: tuple[int, int]) -> Path:
    """mu = [m, -m] / 255, m the mean of the pixels in ``rows`` x ``cols``: it reads only there."""
    nodes = [
        helper.make_node("Slice", ["obs", "starts", "ends", "axes"], ["region"]),
        helper.make_node("ReduceMean", ["region"], ["mean"], axes=[1, 2, 3], keepdims=1),
        helper.make_node("Reshape", ["mean", "one_by_one"], ["m"]),
        helper.make_node("Mul", ["m", "signs"], ["mu"]),
    ]
    inits = [
        numpy_helper.from_array(np.array([rows[0], cols[0]], np.int64), "starts"),
        numpy_helper.from_array(np.array([rows[1], cols[1]], np.int64), "ends"),
        numpy_helper.from_array(np.array([1, 2], np.int64), "axes"),
        numpy_helper.from_array(np.array([1, 1], np.int64), "one_by_one"),
        numpy_helper.from_array(np.array([[1.0, -1.0]], np.float32) / 255.0, "signs"),
    ]
    graph = helper.make_graph(
        nodes, "region_reader",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [1, SIZE, SIZE, 3])],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def _frame() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)


def test_a_policy_that_ignores_the_frame_has_a_zero_occlusion_map(tmp_path: Path) -> None:
    policy = OnnxPolicy.load(policy_models.constant(tmp_path / "c.onnx", (0.3, -0.2), size=SIZE))
    mu, heat = _saliency().occlusion_map(policy, _frame(), patch=8, stride=4)
    assert np.allclose(mu, [0.3, -0.2])
    assert heat.shape == (SIZE, SIZE)
    assert np.all(heat == 0.0)


def test_the_map_of_a_policy_that_reads_one_region_peaks_there(tmp_path: Path) -> None:
    rows, cols = (30, 38), (10, 18)
    policy = OnnxPolicy.load(_region_reader(tmp_path / "r.onnx", rows, cols))
    frame = np.full((SIZE, SIZE, 3), 250, np.uint8)  # far from the patch's grey everywhere
    _, heat = _saliency().occlusion_map(policy, frame, patch=8, stride=2)
    peak = np.unravel_index(np.argmax(heat), heat.shape)
    assert rows[0] <= peak[0] < rows[1] and cols[0] <= peak[1] < cols[1]
    inside = heat[rows[0]:rows[1], cols[0]:cols[1]]
    assert inside.min() > 0.0
    far = heat.copy()
    far[rows[0] - 8:rows[1] + 8, cols[0] - 8:cols[1] + 8] = 0.0  # beyond a patch of it
    assert np.all(far == 0.0)
    assert inside.mean() > 2 * heat.mean()
