"""``jetbot-train ensemble``: one ONNX policy whose wheel commands are the mean of several
policies' commands, for policies trained apart on the same task and frame contract (seeds
of one recipe). It is still one image in, ``mu`` out: the runtime, ``eval`` and the export
contract see an ordinary policy, and its inference costs the members' together.

Each member is read once (``safe_file``, as the runtime reads a policy) and must declare
the same contract as the first: the ``jetbot_rt.*`` metadata keys of ``CONTRACT``, the same
input (dtype and shape, the batch free or fixed alike), the same opset. The result is
checked as the runtime checks a policy and against the members on random inputs before it
replaces ``--out``."""

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
PARITY_TOLERANCE = 1e-5
PARITY_BATCH = 4


def _action_name(graph: onnx.GraphProto) -> str:
    names = [o.name for o in graph.output]
    return "mu" if "mu" in names else names[0]


def _member(path: Path) -> tuple[bytes, onnx.ModelProto]:
    data = safe_file.read_bytes(path, "policy", MAX_MODEL_BYTES)
    try:
        proto = onnx.load_model_from_string(data)
        onnx.checker.check_model(proto)
    except Exception as exc:  # onnx raises several unrelated types for a bad file
        raise UsageError(f"policy {shown(path)}: not a valid ONNX model ({first_line(exc)})"
                         ) from None
    if len(proto.graph.input) != 1 or not proto.graph.output:
        raise UsageError(f"policy {shown(path)}: expected one image input and an action "
                         f"output, found {len(proto.graph.input)} inputs and "
                         f"{len(proto.graph.output)} outputs")
    return data, proto


def _contract(proto: onnx.ModelProto) -> dict[str, Any]:
    metadata = {p.key: p.value for p in proto.metadata_props}
    return {
        **{key: metadata.get(META_PREFIX + key) for key in CONTRACT},
        "input": _tensor_type(proto.graph.input[0]),
        "action output": _tensor_type(next(o for o in proto.graph.output
                                           if o.name == _action_name(proto.graph))),
        "opset": sorted((o.domain, o.version) for o in proto.opset_import),
    }


def _tensor_type(value: onnx.ValueInfoProto) -> tuple[int, tuple[int | str, ...]]:
    tensor = value.type.tensor_type
    dims = tuple(d.dim_value if d.HasField("dim_value") else "N" for d in tensor.shape.dim)
    return tensor.elem_type, dims


def merged_model(protos: list[onnx.ModelProto], names: list[str]) -> onnx.ModelProto:
    """The graph that feeds the first member's input to every member and outputs ``mu``,
    the mean of their action outputs; the first member's metadata, with ``ENSEMBLE_KEY``."""
    first = protos[0].graph
    image = first.input[0].name
    nodes: list[onnx.NodeProto] = []
    initializers: list[onnx.TensorProto] = []
    value_info: list[onnx.ValueInfoProto] = []
    actions = []
    for index, proto in enumerate(protos):
        prefix = f"m{index}/"
        renamed = compose.add_prefix(proto, prefix).graph
        own_input = renamed.input[0].name
        for node in renamed.node:
            node.input[:] = [image if name == own_input else name for name in node.input]
        nodes.extend(renamed.node)
        initializers.extend(renamed.initializer)
        value_info.extend(renamed.value_info)
        actions.append(prefix + _action_name(proto.graph))
    nodes.append(helper.make_node("Mean", actions, ["mu"], name="ensemble_mean"))
    action = next(o for o in first.output if o.name == _action_name(first))
    output = helper.make_tensor_value_info("mu", action.type.tensor_type.elem_type,
                                           [d.dim_value if d.HasField("dim_value")
                                            else (d.dim_param or None)
                                            for d in action.type.tensor_type.shape.dim])
    graph = helper.make_graph(nodes, "jetbot_rt_ensemble", [first.input[0]], [output],
                              initializers, value_info=value_info)
    model = helper.make_model(graph, opset_imports=protos[0].opset_import,
                              ir_version=max(p.ir_version for p in protos),
                              producer_name="jetbot-train ensemble")
    metadata = {p.key: p.value for p in protos[0].metadata_props}
    metadata[ENSEMBLE_KEY] = f"mean of {len(protos)}: " + ", ".join(names)
    helper.set_model_props(model, metadata)
    onnx.checker.check_model(model)
    return model


def parity_error(members: list[bytes], ensemble: bytes, out: Path, seed: int = 0) -> float:
    """Largest |ensemble - mean of the members| over ``PARITY_BATCH`` random inputs; first
    the ensemble passes the runtime's checks of a policy (its input, action, max_speed)."""
    import onnxruntime as ort

    sessions = [ort.InferenceSession(data, providers=["CPUExecutionProvider"])
                for data in (*members, ensemble)]
    metadata = dict(sessions[-1].get_modelmeta().custom_metadata_map)
    OnnxPolicy.input_spec(sessions[-1], shown(out), PolicyConfig(), metadata)
    OnnxPolicy.action_output_of(sessions[-1], shown(out))
    check_max_speed(shown(out), metadata)
    model_input = sessions[-1].get_inputs()[0]
    batch = PARITY_BATCH if not isinstance(model_input.shape[0], int) else model_input.shape[0]
    shape = [batch, *model_input.shape[1:]]
    rng = np.random.default_rng(seed)
    if model_input.type == "tensor(uint8)":
        x = rng.integers(0, 256, shape, dtype=np.uint8)
    else:
        x = (rng.random(shape) * 255.0).astype(np.float16 if "float16" in model_input.type
                                                 else np.float32)
    outs = []
    for session in sessions:
        feed = {session.get_inputs()[0].name: x}
        chosen = next((o for o in session.get_outputs() if o.name == "mu"),
                      session.get_outputs()[0])
        outs.append(np.asarray(session.run([chosen.name], feed)[0], np.float64))
    return float(np.max(np.abs(outs[-1] - np.mean(outs[:-1], axis=0))))


def ensemble_policies(paths: list[str | Path], out: str | Path) -> dict[str, Any]:
    """Write ``out``, the mean of the policies at ``paths`` (two or more); returns what was
    written: ``out``, ``members``, ``parity_error``. Every defect is a ``UsageError``."""
    paths = [Path(p) for p in paths]
    out = Path(out)
    if len(paths) < 2:
        raise UsageError(f"an ensemble needs two or more policies, got {len(paths)}")
    if out.is_dir():
        raise UsageError(f"--out {shown(out)} is a directory, expected an .onnx file path")
    if any(os.path.lexists(p) and out.exists() and os.path.samefile(p, out) for p in paths):
        raise UsageError(f"--out {shown(out)} is one of the members: write it elsewhere")
    read = [_member(p) for p in paths]
    first = _contract(read[0][1])
    for path, (_, proto) in zip(paths[1:], read[1:], strict=True):
        other = _contract(proto)
        for key in first:
            if other[key] != first[key]:
                raise UsageError(f"policy {shown(path)}: its {key} ({other[key]!r}) is not "
                                 f"{shown(paths[0])}'s ({first[key]!r}); an ensemble's "
                                 "members share one contract")
    model = merged_model([proto for _, proto in read], ["/".join(p.parts[-2:]) for p in paths])
    data = model.SerializeToString()
    error = parity_error([d for d, _ in read], data, out)
    if not error < PARITY_TOLERANCE:
        raise UsageError(f"ensemble parity check failed: {error:.3g} from the members' mean")
    write_model(out, data)
    return {"out": str(out), "members": [str(p) for p in paths], "parity_error": error}
