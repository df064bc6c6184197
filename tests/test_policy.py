import numpy as np
import onnx
import policy_models
import pytest
from onnx import TensorProto, helper, numpy_helper

from jetbot_rt.config.sections import PolicyConfig
from jetbot_rt.errors import Fault, UsageError
from jetbot_rt.runtime.policy import MAX_INPUT_SIDE, OnnxPolicy, provider_options

RED = np.zeros((224, 224, 3), np.uint8)
RED[..., 0] = 255


def channel_probe(path, layout="NHWC", size=224, metadata=None, reduce="ReduceMean",
                  height=None):
    """mu = [mean of channel 0, mean of channel 2] as the model sees its input (or another
    reduction over the image). ``size`` is the width, and the height unless ``height``."""
    height = size if height is None else height
    axes = [1, 2] if layout == "NHWC" else [2, 3]
    shape = [1, height, size, 3] if layout == "NHWC" else [1, 3, height, size]
    graph = helper.make_graph(
        [
            helper.make_node(reduce, ["obs"], ["means"], axes=axes, keepdims=0),
            helper.make_node("Gather", ["means", "pick"], ["mu"], axis=1),
        ],
        "probe",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])],
        [numpy_helper.from_array(np.array([0, 2], np.int64), "pick")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 16)])
    model.ir_version = 8
    for key, value in (metadata or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(model, str(path))
    return path


def test_defaults_without_metadata_are_rl_games_nhwc_rgb_0_255(tmp_path):
    policy = OnnxPolicy.load(channel_probe(tmp_path / "p.onnx"))
    info = policy.describe()
    assert (info["layout"], info["color_order"], info["pixel_range"]) == ("NHWC", "RGB", "0-255")
    assert info["size"] == [224, 224] and info["dtype"] == "float32"
    assert policy.infer(RED) == pytest.approx([255.0, 0.0])


def test_nchw_small_input_is_resized(tmp_path):
    policy = OnnxPolicy.load(channel_probe(tmp_path / "p.onnx", layout="NCHW", size=64))
    assert policy.spec.layout == "NCHW" and policy.spec.width == 64
    frame = np.zeros((480, 640, 3), np.uint8)
    frame[..., 2] = 200
    assert policy.infer(frame) == pytest.approx([0.0, 200.0])


def test_a_frame_of_another_size_is_area_averaged_not_sampled(tmp_path):
    policy = OnnxPolicy.load(channel_probe(tmp_path / "p.onnx", size=64, reduce="ReduceMax"))
    frame = np.zeros((720, 1280, 3), np.uint8)
    for k in range(3):  # 3-pixel stripes, 3.3 periods per output pixel
        frame[:, k::6, 0] = 255
    # area averaging leaves 10 or 11 white pixels of 20: grey everywhere (at most 140);
    # nearest, linear, cubic and Lanczos sampling keep full-white pixels (255)
    assert policy.infer(frame)[0] <= 141


def test_metadata_input_size_must_match_the_graph(tmp_path):
    path = channel_probe(tmp_path / "p.onnx", size=64, metadata={"jetbot_rt.input_size": "56x56"})
    with pytest.raises(UsageError, match=r"metadata says input size '56x56'.* is 64x64"):
        OnnxPolicy.load(path)


def test_metadata_bgr_and_unit_range(tmp_path):
    meta = {"jetbot_rt.color_order": "BGR", "jetbot_rt.pixel_range": "0-1",
            "jetbot_rt.max_speed": "0.25"}
    policy = OnnxPolicy.load(channel_probe(tmp_path / "p.onnx", metadata=meta))
    # red arrives in the model's channel 2 when it asks for BGR, scaled to 1.0
    assert policy.infer(RED) == pytest.approx([0.0, 1.0])
    assert policy.max_speed == 0.25


def test_config_overrides_metadata(tmp_path):
    meta = {"jetbot_rt.color_order": "BGR"}
    config = PolicyConfig(color_order="RGB", pixel_range="-1-1")
    policy = OnnxPolicy.load(channel_probe(tmp_path / "p.onnx", metadata=meta), config)
    assert policy.infer(RED) == pytest.approx([1.0, -1.0])


def test_mu_output_is_chosen_over_first_output(tmp_path):
    path = policy_models.constant(tmp_path / "c.onnx", (0.3, -0.4))
    policy = OnnxPolicy.load(path)
    assert policy.action_output == "mu"
    assert OnnxPolicy.load(path).session.get_outputs()[0].name == "value"
    assert policy.infer(RED) == pytest.approx([0.3, -0.4])


def test_first_output_when_no_mu(tmp_path):
    policy = OnnxPolicy.load(policy_models.raise_when_dark(tmp_path / "r.onnx", (0.2, 0.1)))
    assert policy.action_output == "mu_out"
    assert policy.infer(RED) == pytest.approx([0.2, 0.1])


def test_inference_error_is_a_fault(tmp_path):
    policy = OnnxPolicy.load(policy_models.raise_when_dark(tmp_path / "r.onnx"))
    with pytest.raises(Fault, match="policy inference failed"):
        policy.infer(np.zeros((224, 224, 3), np.uint8))


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (policy_models.three_actions, "expected 2 actions [left, right] in output mu, found"),
        (policy_models.vector_input, "expected an image input [N,H,W,3] or [N,3,H,W]"),
        (policy_models.int_input, "expected input dtype float32, float16 or uint8, found"),
    ],
)
def test_unsupported_models(tmp_path, build, message):
    path = build(tmp_path / "m.onnx")
    with pytest.raises(UsageError) as info:
        OnnxPolicy.load(path)
    assert message in str(info.value) and str(path) in str(info.value)


def test_three_actions_with_a_symbolic_batch_are_refused_at_load(tmp_path):
    path = policy_models.three_actions(tmp_path / "m.onnx", batch="N")
    with pytest.raises(UsageError, match=r"expected 2 actions \[left, right\] in output mu"):
        OnnxPolicy.load(path)


def test_tensorrt_gets_an_engine_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("JETBOT_RT_CACHE_DIR", str(tmp_path))
    options = provider_options(["TensorrtExecutionProvider", "CPUExecutionProvider"])
    assert options[0] == ("TensorrtExecutionProvider", {
        "trt_engine_cache_enable": "True", "trt_engine_cache_path": str(tmp_path / "tensorrt")})
    assert options[1] == "CPUExecutionProvider"


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(UsageError, match="no such file"):
        OnnxPolicy.load(tmp_path / "missing.onnx")
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"\x08\x07 this is not a protobuf model")
    with pytest.raises(UsageError, match="not a loadable ONNX model"):
        OnnxPolicy.load(corrupt)


class TestMetadataThatCannotBeHonoured:
    @pytest.mark.parametrize("metadata", [{"jetbot_rt.color_order": "GBR"},
                                          {"jetbot_rt.pixel_range": "0-65535"}])
    def test_unsupported_colour_order_or_range_is_refused_at_load(self, tmp_path, metadata):
        path = channel_probe(tmp_path / "p.onnx", metadata=metadata)
        with pytest.raises(UsageError, match="unsupported metadata"):
            OnnxPolicy.load(path)


class TestWhatTheSessionIsGiven:
    """The settings the runtime promises onnxruntime gets, read back from the live session,
    and the paths it derives (mutants of these survived the behavioural tests)."""

    def test_threads_and_no_spinning(self, tmp_path):
        policy = OnnxPolicy.load(channel_probe(tmp_path / "p.onnx"), threads=2)
        options = policy.session.get_session_options()
        assert (options.intra_op_num_threads, options.inter_op_num_threads) == (2, 2)
        for key in ("session.intra_op.allow_spinning", "session.inter_op.allow_spinning"):
            assert options.get_session_config_entry(key) == "0"

    def test_bundled_policy_and_cache_paths(self, monkeypatch, tmp_path):
        from pathlib import Path

        from jetbot_rt.runtime.policy import bundled_policy_path, tensorrt_cache_dir

        bundled = bundled_policy_path()
        assert bundled.name == "forward.onnx" and bundled.parent.name == "policies"
        assert OnnxPolicy.load(bundled).spec.layout == "NHWC"
        monkeypatch.delenv("JETBOT_RT_CACHE_DIR", raising=False)
        monkeypatch.setenv("HOME", str(tmp_path))
        assert tensorrt_cache_dir() == Path(tmp_path) / ".cache" / "jetbot_rt"

    @pytest.mark.parametrize("declared", ["96x96", "64x63", "6x64"])
    def test_a_declared_size_other_than_the_graphs_is_refused(self, tmp_path, declared):
        path = channel_probe(tmp_path / "p.onnx", size=64,
                             metadata={"jetbot_rt.input_size": declared})
        with pytest.raises(UsageError, match="metadata says input size"):
            OnnxPolicy.load(path)
        ok = channel_probe(tmp_path / "ok.onnx", size=64,
                           metadata={"jetbot_rt.input_size": "64x64"})
        assert OnnxPolicy.load(ok).spec.width == 64


def symbolic_batch_actions(path, count):
    """Input and output with a symbolic batch ``N`` (as our exporter writes them): onnxruntime
    cannot fix the output's shape, so its action count shows only when it runs."""
    graph = helper.make_graph(
        [helper.make_node("ReduceMean", ["obs"], ["m"], axes=[1, 2, 3], keepdims=1),
         helper.make_node("Reshape", ["m", "col"], ["m2"]),
         helper.make_node("Add", ["c", "m2"], ["mu"])],
        "symbolic",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["N", 32, 32, 3])],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, ["N", count])],
        [numpy_helper.from_array(np.zeros((1, count), np.float32), "c"),
         numpy_helper.from_array(np.array([-1, 1], np.int64), "col")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 16)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


class TestActionCountWithASymbolicBatch:
    def test_three_actions_refused_at_load(self, tmp_path):
        path = symbolic_batch_actions(tmp_path / "m.onnx", 3)
        with pytest.raises(UsageError, match=r"expected 2 actions \[left, right\] in output mu"):
            OnnxPolicy.load(path)

    def test_two_actions_load_and_run(self, tmp_path):
        policy = OnnxPolicy.load(symbolic_batch_actions(tmp_path / "m.onnx", 2))
        assert policy.infer(np.zeros((32, 32, 3), np.uint8)).tolist() == [0.0, 0.0]

    @pytest.mark.parametrize("values", [1, 3])
    def test_a_wrong_count_from_an_unknown_width_is_a_fault_when_it_runs(self, tmp_path,
                                                                         values):
        # mu = Tile(c, [batch, 1]) with c one value: the repeats come from the input's shape at
        # run time, so onnxruntime cannot tell the output's width before it runs
        graph = helper.make_graph(
            [helper.make_node("Shape", ["obs"], ["shape"]),
             helper.make_node("Slice", ["shape", "zero", "one"], ["batch"]),
             helper.make_node("Concat", ["batch", "one"], ["repeats"], axis=0),
             helper.make_node("Tile", ["c", "repeats"], ["mu"])],
            "tiled",
            [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["N", 32, 32, 3])],
            [helper.make_tensor_value_info("mu", TensorProto.FLOAT, None)],
            [numpy_helper.from_array(np.zeros((1, values), np.float32), "c"),
             numpy_helper.from_array(np.array([0], np.int64), "zero"),
             numpy_helper.from_array(np.array([1], np.int64), "one")],
        )
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 16)])
        model.ir_version = 8
        onnx.save(model, str(tmp_path / "m.onnx"))
        policy = OnnxPolicy.load(tmp_path / "m.onnx")
        with pytest.raises(Fault, match=f"policy gave {values} action values, expected 2"):
            policy.infer(np.zeros((32, 32, 3), np.uint8))


@pytest.mark.parametrize("stated", ["NWHC", "nhwc", "HWC"])
def test_a_metadata_layout_that_is_not_one_is_refused_unless_config_overrides(tmp_path, stated):
    path = channel_probe(tmp_path / "p.onnx", metadata={"jetbot_rt.layout": stated})
    with pytest.raises(UsageError, match=f"layout = '{stated}' is not one of NHWC, NCHW"):
        OnnxPolicy.load(path)
    assert OnnxPolicy.load(path, PolicyConfig(layout="NHWC")).spec.layout == "NHWC"


class TestClip:
    def test_clip_needs_a_float_input(self, tmp_path):
        graph = helper.make_graph(
            [helper.make_node("Cast", ["obs"], ["f"], to=TensorProto.FLOAT),
             helper.make_node("ReduceMean", ["f"], ["m"], axes=[1, 2], keepdims=0),
             helper.make_node("Gather", ["m", "pick"], ["mu"], axis=1)],
            "uint8_input", [helper.make_tensor_value_info("obs", TensorProto.UINT8,
                                                          [1, 8, 8, 3])],
            [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])],
            [numpy_helper.from_array(np.array([0, 2], np.int64), "pick")],
        )
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 16)])
        model.ir_version = 8
        onnx.save(model, str(tmp_path / "u8.onnx"))
        with pytest.raises(UsageError, match=r"\[policy\] clip needs a float input"):
            OnnxPolicy.load(tmp_path / "u8.onnx", PolicyConfig(clip=5.0))
        assert OnnxPolicy.load(tmp_path / "u8.onnx").infer(RED[:8, :8]).tolist() == [255.0, 0.0]
        clipped = OnnxPolicy.load(channel_probe(tmp_path / "f.onnx"), PolicyConfig(clip=5.0))
        assert clipped.infer(RED).tolist() == [5.0, 0.0]


def sized_probe(path, width, height):
    """An NHWC float model of input ``width`` x ``height`` (nothing is allocated at load)."""
    return channel_probe(path, size=width, height=height)


class TestUntrustedModels:
    """A model file is input like any other: what it declares is checked at load, and every
    defect is a ``UsageError`` (exit 2), never a fault once driving (exit 3)."""

    @pytest.mark.parametrize(("width", "height"), [(4097, 8), (8, 4097), (20000, 20000),
                                                   (2**31, 2**31)])
    def test_an_input_larger_than_the_cap_is_refused_at_load(self, tmp_path, width, height):
        path = sized_probe(tmp_path / "big.onnx", width, height)
        with pytest.raises(UsageError) as info:
            OnnxPolicy.load(path)
        assert str(info.value) == (f"policy {path}: input obs is {width}x{height}; the runtime "
                                   f"takes at most {MAX_INPUT_SIDE} pixels a side")

    def test_the_cap_itself_loads(self, tmp_path):
        assert MAX_INPUT_SIDE == 4096
        spec = OnnxPolicy.load(sized_probe(tmp_path / "cap.onnx", 4096, 4096)).spec
        assert (spec.width, spec.height) == (4096, 4096)

    def test_jetbot_rt_run_refuses_an_absurd_input_size_with_exit_2(self, tmp_path):
        import subprocess

        from runner import JETBOT_RT

        path = sized_probe(tmp_path / "big.onnx", 20000, 20000)
        proc = subprocess.run([JETBOT_RT, "run", "--backend", "sim", "--duration", "1",
                               "--policy", str(path)], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.count("\n") == 1 and "at most 4096 pixels a side" in proc.stderr

    @pytest.mark.parametrize("stated", ["nan", "inf", "0", "-0.1", "1.0000001", "fast", ""])
    def test_a_max_speed_that_is_not_in_0_1_is_refused(self, tmp_path, stated):
        path = channel_probe(tmp_path / "p.onnx", metadata={"jetbot_rt.max_speed": stated})
        with pytest.raises(UsageError) as info:
            OnnxPolicy.load(path)
        assert str(info.value) == (f"policy {path}: its metadata jetbot_rt.max_speed = "
                                   f"{stated!r} is not a number in (0, 1] (fix the export)")

    @pytest.mark.parametrize(("stated", "value"), [("1", 1.0), ("1e-3", 0.001), (None, None)])
    def test_a_max_speed_in_0_1_is_the_models(self, tmp_path, stated, value):
        metadata = {} if stated is None else {"jetbot_rt.max_speed": stated}
        path = channel_probe(tmp_path / "p.onnx", metadata=metadata)
        assert OnnxPolicy.load(path).max_speed == value

    def test_metadata_that_is_not_utf8_is_refused(self, tmp_path):
        path = channel_probe(tmp_path / "p.onnx", metadata={"jetbot_rt.task": "QQQQ"})
        path.write_bytes(path.read_bytes().replace(b"QQQQ", b"\xff\xfe\x80Q"))
        with pytest.raises(UsageError, match="metadata or input and output names are not UTF-8"):
            OnnxPolicy.load(path)

    @pytest.mark.parametrize("kind", ["fifo", "dev-zero", "directory"])
    def test_a_path_that_is_not_a_regular_file_is_refused_without_blocking(self, tmp_path,
                                                                           kind):
        import os
        import threading

        path = tmp_path / "p.onnx"
        if kind == "fifo":
            os.mkfifo(path)
        elif kind == "dev-zero":
            path.symlink_to("/dev/zero")
        else:
            path.mkdir()
        errors = []

        def load():
            try:
                OnnxPolicy.load(path)
            except UsageError as exc:
                errors.append(str(exc))

        worker = threading.Thread(target=load, daemon=True)
        worker.start()
        worker.join(20)
        assert not worker.is_alive(), "load blocked"
        expected = "a directory" if kind == "directory" else "not a regular file"
        assert errors == [f"cannot read policy {path}: {expected}"]

    def test_a_path_that_is_not_utf8_still_loads(self, tmp_path):
        import os

        source = channel_probe(tmp_path / "p.onnx")
        name = os.path.join(os.fsencode(tmp_path), b"\xff.onnx")
        os.rename(source, name)
        policy = OnnxPolicy.load(os.fsdecode(name))
        assert policy.infer(RED).tolist() == [255.0, 0.0]
        assert policy.describe()["path"].endswith("\\xff.onnx")

    def test_a_long_metadata_value_is_cut_in_the_message(self, tmp_path):
        path = channel_probe(tmp_path / "p.onnx", metadata={"jetbot_rt.color_order": "B" * 41})
        with pytest.raises(UsageError) as info:
            OnnxPolicy.load(path)
        assert str(info.value) == (f"policy {path}: unsupported metadata color_order="
                                   f"'{'B' * 40}'... pixel_range='0-255'")
        path = channel_probe(tmp_path / "p.onnx", metadata={"jetbot_rt.color_order": "B" * 40})
        with pytest.raises(UsageError, match=f"color_order='{'B' * 40}' pixel_range"):
            OnnxPolicy.load(path)

    def test_a_file_larger_than_protobufs_limit_is_refused_before_it_is_read(self, tmp_path):
        import os

        from jetbot_rt.runtime.policy import MAX_MODEL_BYTES

        assert MAX_MODEL_BYTES == 2 * 1024**3
        path = tmp_path / "huge.onnx"
        with open(path, "wb") as file:  # sparse: nothing is written
            file.truncate(MAX_MODEL_BYTES + 1)
        with pytest.raises(UsageError) as info:
            OnnxPolicy.load(path)
        assert str(info.value) == f"policy {path} is larger than 2 GiB: not an ONNX model"
        os.truncate(path, MAX_MODEL_BYTES)  # at the limit: read, and refused by onnxruntime
        with pytest.raises(UsageError, match="not a loadable ONNX model"):
            OnnxPolicy.load(path)
