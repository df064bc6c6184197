"""``jetbot-train ensemble``: one ONNX policy whose wheel commands are the mean of several
policies' commands, for policies trained apart on the same task and frame contract (seeds
of one recipe). It is still one image in, ``mu`` out: the runtime, ``eval`` and the export
contract see an ordinary policy, and its inference costs the members' together.

Each member is read once (``safe_file``, as the runtime reads a policy), must be a plain
graph (standard operators, no control flow, local functions or sparse weights: what
``jetbot-train export`` writes and more) with one image input and float32 actions, and must
declare the same contract as the first: the ``jetbot_rt.*`` metadata keys of ``CONTRACT``,
the same input (dtype and shape, the batch free or fixed alike), the same opset. The result
is checked as the runtime checks a policy and against the members on random inputs before
it replaces ``--out``; any failure on the way is one line."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import compose, helper

from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import shown
from jetbot_rt.config.sections import PolicyConfig
from jetbot_rt.errors import UsageError, first_line
from jetbot_rt.runtime.policy import MAX_MODEL_BYTES, META_PREFIX, OnnxPolicy, check_max_speed
from jetbot_rt.train.export import write_model

CONTRACT = ("layout", "input_size", "color_order", "pixel_range", "max_speed", "task",
            "action", "deadband_lift")
"""Metadata keys every member must state alike (or all leave out)."""
ENSEMBLE_KEY = META_PREFIX + "ensemble"
IMAGE = "obs"
"""The ensemble's input (a name no member's prefixed tensor and no output can have)."""
PARITY_TOLERANCE = 1e-5
"""Absolute, relative where the members' mean exceeds 1 (as ``export``'s check)."""
PARITY_BATCH = 4
MAX_BATCH = 64
MAX_INPUT_VALUES = 16 * 1024 * 1024
"""A fixed batch or an input larger than this is no camera policy's: refused before any
random input is made for the parity check."""
STANDARD_DOMAINS = ("", "ai.onnx")


def _action_name(graph: onnx.GraphProto) -> str:
    names = [o.name for o in graph.output]
    return "mu" if "mu" in names else names[0]


def _image_input(graph: onnx.GraphProto) -> onnx.ValueInfoProto | None:
    """The one input that is not an initializer (torch may list its weights as inputs)."""
    weights = {t.name for t in graph.initializer}
    inputs = [i for i in graph.input if i.name not in weights]
    return inputs[0] if len(inputs) == 1 else None


def _plain_graph_problem(proto: onnx.ModelProto) -> str | None:
    if proto.functions:
        return "it defines local functions"
    if proto.graph.sparse_initializer:
        return "it holds sparse weights"
    for node in proto.graph.node:
        if node.domain not in STANDARD_DOMAINS:
            return f"its node {node.name or node.op_type} is of the domain {node.domain!r}"
        if any(a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
               for a in node.attribute):
            return f"its node {node.name or node.op_type} ({node.op_type}) holds a subgraph"
    if _image_input(proto.graph) is None:
        return f"expected one image input, found {len(proto.graph.input)} inputs"
    if not proto.graph.output:
        return "it has no output"
    action = next(o for o in proto.graph.output if o.name == _action_name(proto.graph))
    if action.type.tensor_type.elem_type != onnx.TensorProto.FLOAT:
        return f"its action output {action.name} is not float32"
    batch, *rest = _tensor_type(_image_input(proto.graph))[1] or ("N",)
    if not rest or not all(isinstance(d, int) and d > 0 for d in rest):
        return "its input's size is not fixed"
    if (isinstance(batch, int) and not 0 < batch <= MAX_BATCH) or \
            int(np.prod(rest)) * (batch if isinstance(batch, int) else 1) > MAX_INPUT_VALUES:
        return "its input is larger than a camera policy's"
    return None


def _member(path: Path) -> tuple[bytes, onnx.ModelProto]:
    data = safe_file.read_bytes(path, "policy", MAX_MODEL_BYTES)
    try:
        proto = onnx.load_model_from_string(data)
        onnx.checker.check_model(proto)
    except Exception as exc:  # onnx raises several unrelated types for a bad file
        raise UsageError(f"policy {shown(path)}: not a valid ONNX model ({first_line(exc)})"
                         ) from None
    problem = _plain_graph_problem(proto)
    if problem:
        raise UsageError(f"policy {shown(path)}: {problem}; an ensemble takes plain graphs of "
                         "one image input and float32 actions, as jetbot-train exports")
    return data, proto


def _contract(proto: onnx.ModelProto) -> dict[str, Any]:
    metadata = {p.key: p.value for p in proto.metadata_props}
    image = _image_input(proto.graph)
    assert image is not None  # _member checked it
    return {
        **{key: metadata.get(META_PREFIX + key) for key in CONTRACT},
        "input": _tensor_type(image),
        "action output": _tensor_type(next(o for o in proto.graph.output
                                           if o.name == _action_name(proto.graph))),
        "opset": sorted((o.domain, o.version) for o in proto.opset_import),
    }


def _tensor_type(value: onnx.ValueInfoProto) -> tuple[int, tuple[int | str, ...]]:
    tensor = value.type.tensor_type
    dims = tuple(d.dim_value if d.HasField("dim_value") else "N" for d in tensor.shape.dim)
    return tensor.elem_type, dims


def merged_model(protos: list[onnx.ModelProto], names: list[str]) -> onnx.ModelProto:
    """The graph that feeds one image (``IMAGE``, typed as the first member's input) to
    every member and outputs ``mu``, the mean of their action outputs; the first member's
    metadata, with ``ENSEMBLE_KEY``."""
    first = protos[0].graph
    first_image = _image_input(first)
    assert first_image is not None
    image = helper.make_value_info(IMAGE, first_image.type)
    nodes: list[onnx.NodeProto] = []
    initializers: list[onnx.TensorProto] = []
    value_info: list[onnx.ValueInfoProto] = []
    actions = []
    for index, proto in enumerate(protos):
        prefix = f"m{index}/"
        renamed = compose.add_prefix(proto, prefix).graph
        own_image = _image_input(renamed)
        assert own_image is not None
        for node in renamed.node:
            node.input[:] = [IMAGE if name == own_image.name else name for name in node.input]
        nodes.extend(renamed.node)
        initializers.extend(renamed.initializer)
        value_info.extend(renamed.value_info)
        actions.append(prefix + _action_name(proto.graph))
    nodes.append(helper.make_node("Mean", actions, ["mu"], name="ensemble_mean"))
    action = next(o for o in first.output if o.name == _action_name(first))
    output = helper.make_value_info("mu", action.type)
    graph = helper.make_graph(nodes, "jetbot_rt_ensemble", [image], [output], initializers,
                              value_info=value_info)
    model = helper.make_model(graph, opset_imports=protos[0].opset_import,
                              ir_version=max(p.ir_version for p in protos),
                              producer_name="jetbot-train ensemble")
    metadata = {p.key: p.value for p in protos[0].metadata_props}
    metadata[ENSEMBLE_KEY] = f"mean of {len(protos)}: " + ", ".join(names)
    helper.set_model_props(model, metadata)
    onnx.checker.check_model(model)
    return model


def parity_error(members: list[bytes], ensemble: bytes, out: Path, seed: int = 0) -> float:
    """Largest |ensemble - mean of the members| (relative above 1) over random inputs;
    first the ensemble passes the runtime's checks of a policy (input, action, max_speed)."""
    import onnxruntime as ort

    sessions = [ort.InferenceSession(data, providers=["CPUExecutionProvider"])
                for data in (*members, ensemble)]
    metadata = dict(sessions[-1].get_modelmeta().custom_metadata_map)
    OnnxPolicy.input_spec(sessions[-1], shown(out), PolicyConfig(), metadata)
    OnnxPolicy.action_output_of(sessions[-1], shown(out))
    check_max_speed(shown(out), metadata)
    model_input = sessions[-1].get_inputs()[0]
    batch = model_input.shape[0] if isinstance(model_input.shape[0], int) else PARITY_BATCH
    shape = [batch, *model_input.shape[1:]]
    rng = np.random.default_rng(seed)
    if model_input.type == "tensor(uint8)":
        x: np.ndarray = rng.integers(0, 256, shape, dtype=np.uint8)
    else:
        x = (rng.random(shape) * 255.0).astype(np.float16 if "float16" in model_input.type
                                                 else np.float32)
    outs = []
    for session in sessions:
        feed = {session.get_inputs()[0].name: x}
        action = OnnxPolicy.action_output_of(session, shown(out))
        outs.append(np.asarray(session.run([action], feed)[0], np.float64))
    mean = np.mean(np.stack(outs[:-1]), axis=0)
    return float(np.max(np.abs(outs[-1] - mean) / np.maximum(1.0, np.abs(mean))))


def _check_out(out: Path, paths: list[Path]) -> None:
    try:
        if out.is_dir():
            raise UsageError(f"--out {shown(out)} is a directory, expected an .onnx file path")
        if out.exists() and any(p.exists() and os.path.samefile(p, out) for p in paths):
            raise UsageError(f"--out {shown(out)} is one of the members: write it elsewhere")
    except OSError as exc:
        raise UsageError(f"--out {shown(out)}: {exc.strerror or exc}") from None


def ensemble_policies(paths: list[str | Path], out: str | Path) -> dict[str, Any]:
    """Write ``out``, the mean of the policies at ``paths`` (two or more); returns what was
    written: ``out``, ``members``, ``parity_error``. Every defect is a ``UsageError``."""
    paths = [Path(p) for p in paths]
    out = Path(out)
    if len(paths) < 2:
        raise UsageError(f"an ensemble needs two or more policies, got {len(paths)}")
    _check_out(out, paths)
    read = [_member(p) for p in paths]
    first = _contract(read[0][1])
    for path, (_, proto) in zip(paths[1:], read[1:], strict=True):
        other = _contract(proto)
        for key in first:
            if other[key] != first[key]:
                raise UsageError(f"policy {shown(path)}: its {key} ({other[key]!r}) is not "
                                 f"{shown(paths[0])}'s ({first[key]!r}); an ensemble's "
                                 "members share one contract")
    try:
        model = merged_model([proto for _, proto in read],
                             ["/".join(p.parts[-2:]) for p in paths])
        data = model.SerializeToString()
        error = parity_error([d for d, _ in read], data, out)
    except UsageError:
        raise
    except Exception as exc:  # onnx and onnxruntime raise many types; a member may lie
        raise UsageError(f"cannot build an ensemble of these policies: {first_line(exc)}"
                         ) from None
    if not error < PARITY_TOLERANCE:  # NaN included
        raise UsageError(f"ensemble parity check failed: {error:.3g} from the members' mean")
    write_model(out, data)
    return {"out": str(out), "members": [str(p) for p in paths], "parity_error": error}
