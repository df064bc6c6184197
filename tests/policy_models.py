"""Small ONNX image policies built with onnx.helper, for tests that need a real onnxruntime.

``constant`` returns a fixed ``mu``; the ``*_when_dark`` variants behave normally until the
frame turns black (mean pixel < 1, as the sim's ``blackout`` fault renders it), then hang,
return NaN or fail inside onnxruntime: the fault happens in the real inference call.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 16
SIZE = 56
"""The image input's default side, the bundled policies' 56x56: the sim renders its camera at
the policy's size, and a sim run with a 224x224 policy took 0.8 s of CPU per second of driving
(0.12 s at 56x56), on a 2-core machine that runs two tests at once."""


def _input(layout: str, size: int, elem: int = TensorProto.FLOAT) -> onnx.ValueInfoProto:
    shape = [1, size, size, 3] if layout == "NHWC" else [1, 3, size, size]
    return helper.make_tensor_value_info("obs", elem, shape)


def _save(graph: onnx.GraphProto, path: Path, metadata: dict[str, str] | None = None) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    for key, value in (metadata or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def _mu_from_obs(mu: tuple[float, float], obs: str = "obs") -> list[onnx.NodeProto]:
    """mu = const + 0 * mean(obs): the output depends on the input so no op is folded away."""
    return [
        helper.make_node("ReduceMean", [obs], ["mean"], keepdims=0),
        helper.make_node("Mul", ["mean", "zero"], ["zeroed"]),
        helper.make_node("Add", ["mu_const", "zeroed"], ["mu"]),
    ]


def _mu_initializers(mu: tuple[float, float]) -> list[onnx.TensorProto]:
    return [
        numpy_helper.from_array(np.array([list(mu)], dtype=np.float32), "mu_const"),
        numpy_helper.from_array(np.array(0.0, dtype=np.float32), "zero"),
    ]


def constant(path: Path, mu: tuple[float, float] = (1.0, 1.0), *, layout: str = "NHWC",
             size: int = SIZE, metadata: dict[str, str] | None = None,
             extra_outputs: bool = True) -> Path:
    """Outputs ``mu`` (and rl_games' ``log_std`` and ``value`` when ``extra_outputs``)."""
    nodes = _mu_from_obs(mu)
    outputs = [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])]
    inits = _mu_initializers(mu)
    if extra_outputs:
        nodes.append(helper.make_node("Identity", ["log_std_const"], ["log_std"]))
        nodes.append(helper.make_node("ReduceSum", ["mu"], ["value"], keepdims=1))
        inits.append(numpy_helper.from_array(np.full((1, 2), -1.0, np.float32), "log_std_const"))
        outputs = [
            helper.make_tensor_value_info("value", TensorProto.FLOAT, [1, 1]),
            outputs[0],
            helper.make_tensor_value_info("log_std", TensorProto.FLOAT, [1, 2]),
        ]
    graph = helper.make_graph(nodes, "constant", [_input(layout, size)], outputs, inits)
    return _save(graph, path, metadata)


def _dark_condition() -> list[onnx.NodeProto]:
    return [
        helper.make_node("ReduceMean", ["obs"], ["brightness"], keepdims=0),
        helper.make_node("Less", ["brightness", "one"], ["dark"]),
    ]


def hang_when_dark(path: Path, mu: tuple[float, float] = (1.0, 1.0)) -> Path:
    """A Loop whose trip count is 10^15 on a black frame: inference never returns."""
    body = helper.make_graph(
        [
            helper.make_node("Identity", ["cond_in"], ["cond_out"]),
            helper.make_node("Add", ["acc_in", "step"], ["acc_out"]),
        ],
        "spin",
        [
            helper.make_tensor_value_info("i", TensorProto.INT64, []),
            helper.make_tensor_value_info("cond_in", TensorProto.BOOL, []),
            helper.make_tensor_value_info("acc_in", TensorProto.FLOAT, []),
        ],
        [
            helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
            helper.make_tensor_value_info("acc_out", TensorProto.FLOAT, []),
        ],
        [numpy_helper.from_array(np.array(0.0, np.float32), "step")],
    )
    nodes = [
        *_dark_condition(),
        helper.make_node("Where", ["dark", "many", "once"], ["trips"]),
        helper.make_node("Loop", ["trips", "true", "zero"], ["spun"], body=body),
        helper.make_node("Mul", ["spun", "zero"], ["spun_zero"]),
        helper.make_node("Add", ["mu_const", "spun_zero"], ["mu"]),
    ]
    inits = [
        *_mu_initializers(mu),
        numpy_helper.from_array(np.array(1.0, np.float32), "one"),
        numpy_helper.from_array(np.array(10**15, np.int64), "many"),
        numpy_helper.from_array(np.array(1, np.int64), "once"),
        numpy_helper.from_array(np.array(True), "true"),
    ]
    graph = helper.make_graph(
        nodes, "hang_when_dark", [_input("NHWC", SIZE)],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])], inits,
    )
    return _save(graph, path)


def nan_when_dark(path: Path, mu: tuple[float, float] = (1.0, 1.0)) -> Path:
    nodes = [
        *_dark_condition(),
        helper.make_node("Where", ["dark", "nan", "mu_const"], ["mu_raw"]),
        *_mu_from_obs(mu)[:2],
        helper.make_node("Add", ["mu_raw", "zeroed"], ["mu"]),
    ]
    inits = [
        *_mu_initializers(mu),
        numpy_helper.from_array(np.array(1.0, np.float32), "one"),
        numpy_helper.from_array(np.array(np.nan, np.float32), "nan"),
    ]
    graph = helper.make_graph(
        nodes, "nan_when_dark", [_input("NHWC", SIZE)],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])], inits,
    )
    return _save(graph, path)


def raise_when_dark(path: Path, mu: tuple[float, float] = (1.0, 1.0)) -> Path:
    """Reshapes mu to [1, 2] normally and to [1, 3] on a black frame: onnxruntime raises."""
    nodes = [
        *_dark_condition(),
        helper.make_node("Where", ["dark", "bad_shape", "good_shape"], ["shape"]),
        *_mu_from_obs(mu),
        helper.make_node("Reshape", ["mu", "shape"], ["mu_out"]),
    ]
    inits = [
        *_mu_initializers(mu),
        numpy_helper.from_array(np.array(1.0, np.float32), "one"),
        numpy_helper.from_array(np.array([1, 3], np.int64), "bad_shape"),
        numpy_helper.from_array(np.array([1, 2], np.int64), "good_shape"),
    ]
    graph = helper.make_graph(
        nodes, "raise_when_dark", [_input("NHWC", SIZE)],
        [helper.make_tensor_value_info("mu_out", TensorProto.FLOAT, [1, 2])], inits,
    )
    return _save(graph, path)


def _matmul_work(name: str, mu: tuple[float, float], trip_nodes: list[onnx.NodeProto],
                 trip_inits: list[onnx.TensorProto], path: Path) -> Path:
    """mu after a Loop that multiplies a 64x64 matrix ``trips`` times (``trip_nodes`` make
    ``trips``): inference time grows with the trip count, inside onnxruntime."""
    body = helper.make_graph(
        [
            helper.make_node("Identity", ["cond_in"], ["cond_out"]),
            helper.make_node("MatMul", ["m_in", "w"], ["m_prod"]),
            helper.make_node("Mul", ["m_prod", "decay"], ["m_out"]),
        ],
        "work",
        [
            helper.make_tensor_value_info("i", TensorProto.INT64, []),
            helper.make_tensor_value_info("cond_in", TensorProto.BOOL, []),
            helper.make_tensor_value_info("m_in", TensorProto.FLOAT, [64, 64]),
        ],
        [
            helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
            helper.make_tensor_value_info("m_out", TensorProto.FLOAT, [64, 64]),
        ],
        [
            numpy_helper.from_array(np.eye(64, dtype=np.float32), "w"),
            numpy_helper.from_array(np.array(0.5, np.float32), "decay"),
        ],
    )
    nodes = [
        *trip_nodes,
        *_mu_from_obs(mu)[:2],
        helper.make_node("Loop", ["trips", "true", "m0"], ["m_end"], body=body),
        helper.make_node("ReduceSum", ["m_end"], ["m_sum"], keepdims=0),
        helper.make_node("Mul", ["m_sum", "zero"], ["m_zero"]),
        helper.make_node("Add", ["zeroed", "m_zero"], ["offset"]),
        helper.make_node("Add", ["mu_const", "offset"], ["mu"]),
    ]
    inits = [
        *_mu_initializers(mu),
        *trip_inits,
        numpy_helper.from_array(np.array(True), "true"),
        numpy_helper.from_array(np.ones((64, 64), np.float32), "m0"),
    ]
    graph = helper.make_graph(
        nodes, name, [_input("NHWC", SIZE)],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])], inits,
    )
    return _save(graph, path)


def slow(path: Path, iterations: int, mu: tuple[float, float] = (1.0, 1.0)) -> Path:
    """A constant policy that first multiplies a 64x64 matrix ``iterations`` times."""
    trips = [numpy_helper.from_array(np.array(iterations, np.int64), "trips")]
    return _matmul_work("slow", mu, [], trips, path)

def three_actions(path: Path, batch: int | str = 1) -> Path:
    """``mu`` of shape [batch, 3]; ``batch="N"`` declares a symbolic batch as exporters do."""
    graph = helper.make_graph(
        [helper.make_node("ReduceMean", ["obs"], ["m"], keepdims=0),
         helper.make_node("Add", ["c", "m"], ["mu"])],
        "three", [_input("NHWC", 224)],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [batch, 3])],
        [numpy_helper.from_array(np.zeros((1, 3), np.float32), "c")],
    )
    return _save(graph, path)


def vector_input(path: Path) -> Path:
    graph = helper.make_graph(
        [helper.make_node("ReduceMean", ["obs"], ["m"], keepdims=1),
         helper.make_node("Add", ["c", "m"], ["mu"])],
        "vector", [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [1, 8])],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])],
        [numpy_helper.from_array(np.zeros((1, 2), np.float32), "c")],
    )
    return _save(graph, path)


def int_input(path: Path) -> Path:
    graph = helper.make_graph(
        [helper.make_node("Cast", ["obs"], ["f"], to=TensorProto.FLOAT),
         helper.make_node("ReduceMean", ["f"], ["m"], keepdims=0),
         helper.make_node("Add", ["c", "m"], ["mu"])],
        "int_input", [_input("NHWC", 224, TensorProto.INT32)],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])],
        [numpy_helper.from_array(np.zeros((1, 2), np.float32), "c")],
    )
    return _save(graph, path)


def inf_when_dark(path: Path, mu: tuple[float, float] = (1.0, 1.0)) -> Path:
    """Like ``nan_when_dark``, but the left action becomes +inf on a black frame."""
    nodes = [
        *_dark_condition(),
        helper.make_node("Where", ["dark", "inf_mu", "mu_const"], ["mu_raw"]),
        *_mu_from_obs(mu)[:2],
        helper.make_node("Add", ["mu_raw", "zeroed"], ["mu"]),
    ]
    inits = [
        *_mu_initializers(mu),
        numpy_helper.from_array(np.array(1.0, np.float32), "one"),
        numpy_helper.from_array(np.array([[np.inf, mu[1]]], np.float32), "inf_mu"),
    ]
    graph = helper.make_graph(
        nodes, "inf_when_dark", [_input("NHWC", SIZE)],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])], inits,
    )
    return _save(graph, path)


def slow_when_dark(path: Path, iterations: int, mu: tuple[float, float] = (1.0, 1.0)) -> Path:
    """Like ``slow``, but the 64x64 matrix loop runs ``iterations`` times only on a black frame
    (once otherwise): fast enough for warm-up, slower than a period while the lens is dark."""
    trip_nodes = [
        *_dark_condition(),
        helper.make_node("Where", ["dark", "many", "once"], ["trips"]),
    ]
    trip_inits = [
        numpy_helper.from_array(np.array(1.0, np.float32), "one"),
        numpy_helper.from_array(np.array(iterations, np.int64), "many"),
        numpy_helper.from_array(np.array(1, np.int64), "once"),
    ]
    return _matmul_work("slow_when_dark", mu, trip_nodes, trip_inits, path)

def _mean_graph(name: str, inputs: list, outputs: list, nodes: list | None = None,
                inits: list | None = None) -> onnx.GraphProto:
    return helper.make_graph(nodes or [
        helper.make_node("ReduceMean", ["obs"], ["m"], keepdims=0),
        helper.make_node("Add", ["c", "m"], ["mu"]),
    ], name, inputs, outputs, inits if inits is not None else [
        numpy_helper.from_array(np.zeros((1, 2), np.float32), "c")])


def dynamic_size(path: Path) -> Path:
    """Image input ``[1, h, w, 3]``: no fixed size to resize frames to."""
    obs = helper.make_tensor_value_info("obs", TensorProto.FLOAT, [1, "h", "w", 3])
    mu = helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])
    return _save(_mean_graph("dynamic", [obs], [mu]), path)


def two_inputs(path: Path) -> Path:
    extra = helper.make_tensor_value_info("speed", TensorProto.FLOAT, [1, 1])
    mu = helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])
    nodes = [helper.make_node("ReduceMean", ["obs"], ["m"], keepdims=0),
             helper.make_node("Add", ["c", "m"], ["cm"]),
             helper.make_node("Add", ["cm", "speed"], ["mu"])]
    return _save(_mean_graph("two_inputs", [_input("NHWC", 224), extra], [mu], nodes), path)


def int_output(path: Path) -> Path:
    mu = helper.make_tensor_value_info("mu", TensorProto.INT64, [1, 2])
    nodes = [helper.make_node("ReduceMean", ["obs"], ["m"], keepdims=0),
             helper.make_node("Add", ["c", "m"], ["f"]),
             helper.make_node("Cast", ["f"], ["mu"], to=TensorProto.INT64)]
    return _save(_mean_graph("int_output", [_input("NHWC", 224)], [mu], nodes), path)


def unknown_operator(path: Path) -> Path:
    """A node of a domain onnxruntime does not know: the file parses, no session opens."""
    mu = helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])
    nodes = [helper.make_node("Teleport", ["obs"], ["mu"], domain="com.example.nowhere")]
    model = helper.make_model(
        _mean_graph("unknown_op", [_input("NHWC", 224)], [mu], nodes, []),
        opset_imports=[helper.make_opsetid("", OPSET),
                       helper.make_opsetid("com.example.nowhere", 1)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def rl_games_actor_critic(path: Path, size: int = 224, seed: int = 0) -> Path:
    """rl_games ``actor_critic`` with the reference JetBot cnn: convs 32x8/4, 64x4/2, 64x3/1 (relu),
    mlp [512] elu, mu and value heads, a fixed log_std; NHWC input permuted inside. At 224x224
    it has the reference's 19 M parameters (75 MB); tests use a smaller ``size``."""
    rng = np.random.default_rng(seed)
    weights = []

    def init(name: str, *shape: int) -> str:
        fan_in = int(np.prod(shape[1:])) if len(shape) > 1 else shape[0]
        value = rng.normal(0.0, 1.0 / np.sqrt(fan_in), shape).astype(np.float32)
        weights.append(numpy_helper.from_array(value, name))
        return name

    nodes = [helper.make_node("Transpose", ["obs"], ["x0"], perm=[0, 3, 1, 2])]
    channels, side, x = 3, size, "x0"
    for i, (out, kernel, stride) in enumerate([(32, 8, 4), (64, 4, 2), (64, 3, 1)], start=1):
        nodes.append(helper.make_node(
            "Conv", [x, init(f"conv{i}.w", out, channels, kernel, kernel),
                     init(f"conv{i}.b", out)], [f"c{i}"], strides=[stride, stride]))
        nodes.append(helper.make_node("Relu", [f"c{i}"], [f"x{i}"]))
        channels, side, x = out, (side - kernel) // stride + 1, f"x{i}"
    flat = channels * side * side
    nodes += [
        helper.make_node("Flatten", [x], ["flat"]),
        helper.make_node("Gemm", ["flat", init("mlp.w", 512, flat), init("mlp.b", 512)],
                         ["h"], transB=1),
        helper.make_node("Elu", ["h"], ["hidden"]),
        helper.make_node("Gemm", ["hidden", init("mu.w", 2, 512), init("mu.b", 2)], ["mu"],
                         transB=1),
        helper.make_node("Gemm", ["hidden", init("value.w", 1, 512), init("value.b", 1)],
                         ["value"], transB=1),
        helper.make_node("Constant", [], ["log_std"],
                         value=numpy_helper.from_array(np.zeros((1, 2), np.float32))),
    ]
    graph = helper.make_graph(
        nodes, "rl_games_actor_critic",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [1, size, size, 3])],
        [helper.make_tensor_value_info(name, TensorProto.FLOAT, shape)
         for name, shape in (("mu", [1, 2]), ("log_std", [1, 2]), ("value", [1, 1]))],
        initializer=weights,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 16)])
    model.ir_version = 8  # what onnxruntime 1.19 (the last for Python 3.8) reads
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path
