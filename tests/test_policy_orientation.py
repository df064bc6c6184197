"""Frames reach the model the right way round: rows stay rows, columns stay columns, channels
keep their meaning, in both layouts, with and without a resize.

The probe model returns two chosen input elements, addressed in its own layout, so a frame
fed transposed (height and width swapped), mirrored or with its channels shuffled gives
different numbers. Images are non-square and every pixel is distinct; a square case shows a
transpose that keeps the shape.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from jetbot_rt.runtime.policy import OnnxPolicy

PICKS = [(1, 6, 0), (5, 2, 2)]
"""(row, column, channel) of the two elements the probe returns as ``mu``."""


def element_probe(path: Path, layout: str, height: int, width: int,
                  metadata: dict[str, str] | None = None) -> Path:
    """``mu = [x[p] for p in PICKS]`` where ``x`` is the model's input in ``layout``."""
    if layout == "NHWC":
        shape = [1, height, width, 3]
        flat = [(h * width + w) * 3 + c for h, w, c in PICKS]
    else:
        shape = [1, 3, height, width]
        flat = [c * height * width + h * width + w for h, w, c in PICKS]
    graph = helper.make_graph(
        [
            helper.make_node("Reshape", ["obs", "flat_shape"], ["flat"]),
            helper.make_node("Gather", ["flat", "picks"], ["picked"], axis=0),
            helper.make_node("Reshape", ["picked", "mu_shape"], ["mu"]),
        ],
        "element_probe",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])],
        [
            numpy_helper.from_array(np.array([-1], np.int64), "flat_shape"),
            numpy_helper.from_array(np.array(flat, np.int64), "picks"),
            numpy_helper.from_array(np.array([1, 2], np.int64), "mu_shape"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 16)])
    model.ir_version = 8
    for key, value in {"jetbot_rt.layout": layout, **(metadata or {})}.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def distinct_image(height: int, width: int) -> np.ndarray:
    """Every (row, column, channel) a different value (up to 255 of them)."""
    count = height * width * 3
    assert count <= 256
    return np.arange(count, dtype=np.uint8).reshape(height, width, 3)


def expected(image: np.ndarray, channel_map: tuple[int, int, int] = (0, 1, 2)) -> list[float]:
    return [float(image[h, w, channel_map[c]]) for h, w, c in PICKS]


class TestFramesKeepTheirOrientation:
    @pytest.mark.parametrize("layout", ["NHWC", "NCHW"])
    @pytest.mark.parametrize(("height", "width"), [(6, 8), (8, 7), (8, 8)])
    def test_each_element_arrives_where_the_model_looks(self, tmp_path: Path, layout: str,
                                                        height: int, width: int) -> None:
        policy = OnnxPolicy.load(element_probe(tmp_path / "p.onnx", layout, height, width))
        assert (policy.spec.layout, policy.spec.height, policy.spec.width) == (
            layout, height, width)
        image = distinct_image(height, width)
        assert policy.infer(image).tolist() == expected(image)

    @pytest.mark.parametrize("layout", ["NHWC", "NCHW"])
    def test_bgr_models_get_the_channels_reversed_not_the_pixels_moved(
            self, tmp_path: Path, layout: str) -> None:
        path = element_probe(tmp_path / "p.onnx", layout, 6, 8,
                             {"jetbot_rt.color_order": "BGR"})
        policy = OnnxPolicy.load(path)
        image = distinct_image(6, 8)
        assert policy.infer(image).tolist() == expected(image, channel_map=(2, 1, 0))

    @pytest.mark.parametrize("layout", ["NHWC", "NCHW"])
    def test_a_larger_frame_is_scaled_down_the_right_way_round(self, tmp_path: Path,
                                                               layout: str) -> None:
        # a 12x16 frame for a 6x8 model: 2x2 area averaging, each value known exactly
        policy = OnnxPolicy.load(element_probe(tmp_path / "p.onnx", layout, 6, 8))
        rows, cols = np.mgrid[0:12, 0:16]
        frame = np.stack([10 * rows, 10 * cols, 5 * rows + 3 * cols], axis=-1).astype(np.uint8)
        small_rows, small_cols = np.mgrid[0:6, 0:8]
        want = np.stack([20 * small_rows + 5, 20 * small_cols + 5,
                         10 * small_rows + 6 * small_cols + 4], axis=-1)
        assert policy.infer(frame).tolist() == expected(want)

    def test_pixel_range_scales_without_moving_anything(self, tmp_path: Path) -> None:
        path = element_probe(tmp_path / "p.onnx", "NCHW", 6, 8,
                             {"jetbot_rt.pixel_range": "-1-1"})
        image = distinct_image(6, 8)
        got = OnnxPolicy.load(path).infer(image)
        assert got == pytest.approx([v * 2 / 255 - 1 for v in expected(image)], abs=1e-6)

    @pytest.mark.parametrize(("frame_h", "frame_w"), [(6, 16), (12, 8)])
    def test_a_frame_that_differs_in_one_dimension_is_scaled_too(
            self, tmp_path: Path, frame_h: int, frame_w: int) -> None:
        policy = OnnxPolicy.load(element_probe(tmp_path / "p.onnx", "NCHW", 6, 8))
        rows, cols = np.mgrid[0:frame_h, 0:frame_w]
        frame = np.stack([10 * rows, 10 * cols, 10 * rows], axis=-1).astype(np.uint8)
        fy, fx = frame_h // 6, frame_w // 8  # the scale factor of each dimension: 1 or 2
        row = 10 * (fy * np.arange(6) + (fy - 1) / 2)  # the mean of the rows averaged
        col = 10 * (fx * np.arange(8) + (fx - 1) / 2)
        want = [(row[h], col[w], row[h])[c] for h, w, c in PICKS]
        assert policy.infer(frame).tolist() == want


class TestLayoutPrecedence:
    """Config over metadata over the shape's guess (DESIGN: "Config can override"), on a shape
    that could be either layout."""

    def test_config_then_metadata_then_guess(self, tmp_path: Path) -> None:
        from jetbot_rt.config.sections import PolicyConfig

        ambiguous = element_probe(tmp_path / "p.onnx", "NCHW", 8, 3)  # [1, 3, 8, 3]
        assert OnnxPolicy.load(ambiguous).spec.layout == "NCHW"  # as its metadata states
        nhwc = OnnxPolicy.load(ambiguous, PolicyConfig(layout="NHWC")).spec
        assert (nhwc.layout, nhwc.height, nhwc.width) == ("NHWC", 3, 8)
        model = onnx.load(str(ambiguous))
        del model.metadata_props[:]
        onnx.save(model, str(tmp_path / "bare.onnx"))
        assert OnnxPolicy.load(tmp_path / "bare.onnx").spec.layout == "NHWC"  # rl_games' guess
        nchw = OnnxPolicy.load(tmp_path / "bare.onnx", PolicyConfig(layout="NCHW")).spec
        assert (nchw.layout, nchw.height, nchw.width) == ("NCHW", 8, 3)


def mean_slice_model(path: Path, shape: list[int], axes: list[int]) -> Path:
    """An ONNX model whose ``mu`` is the first two of the input's means over ``axes``: any
    image layout loads, so only the loader's checks of ``shape`` decide."""
    graph = helper.make_graph(
        [helper.make_node("ReduceMean", ["obs"], ["m"], axes=axes, keepdims=0),
         helper.make_node("Slice", ["m", "zero", "two", "one"], ["mu"])],
        "mean_slice", [helper.make_tensor_value_info("obs", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, None])],
        [numpy_helper.from_array(np.array([0], np.int64), "zero"),
         numpy_helper.from_array(np.array([2], np.int64), "two"),
         numpy_helper.from_array(np.array([1], np.int64), "one")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 16)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


class TestColourChannelsCounted:
    @pytest.mark.parametrize("channels", [1, 2, 4])
    def test_an_image_input_without_three_channels_is_refused(self, tmp_path: Path,
                                                               channels: int) -> None:
        from jetbot_rt.config.sections import PolicyConfig
        from jetbot_rt.errors import UsageError

        model = mean_slice_model(tmp_path / "m.onnx", [1, 8, 8, channels], [1, 2])
        with pytest.raises(UsageError, match="expected 3 colour channels in NHWC input"):
            OnnxPolicy.load(model, PolicyConfig(layout="NHWC"))


class TestLayoutGuess:
    @pytest.mark.parametrize("shape", [[1, 8, 8, 4], [1, 8, 8, 1], [1, 1, 8, 8], [1, 2, 8, 2]])
    def test_no_guess_without_a_dimension_of_3(self, tmp_path: Path, shape: list[int]) -> None:
        from jetbot_rt.errors import UsageError

        model = mean_slice_model(tmp_path / "m.onnx", shape, [2, 3])
        with pytest.raises(UsageError, match="cannot tell the image layout"):
            OnnxPolicy.load(model)
