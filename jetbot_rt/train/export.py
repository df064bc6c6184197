"""Checkpoint -> ONNX in the rl_games layout the runtime (and older tools) expect, with
metadata that states how to feed it, and a parity check of onnxruntime against torch."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import nn

import jetbot_rt
from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import shown
from jetbot_rt.errors import UsageError
from jetbot_rt.runtime.actions import DEFAULT_MAX_SPEED
from jetbot_rt.train.checkpoint import load_checkpoint
from jetbot_rt.train.hyperparams import OptionError
from jetbot_rt.train.model import ActorCritic

DEFAULT_OPSET = 16
OPSETS = range(8, 21)
"""The opsets torch's TorchScript exporter writes this network in (outside them it fails after
printing its graph); onnxruntime 1.x reads all of them."""
PARITY_TOLERANCE = 1e-4
ACTION_MEANING = "[left, right] wheel commands in [-1, 1]; duty = max_speed * clamp(mu, -1, 1)"


class ExportError(UsageError):
    """The exported model does not match the trained one (exit 2, one line)."""


def policy_metadata(task: str, max_speed: float, image_size: int) -> dict[str, str]:
    return {
        "jetbot_rt.layout": "NHWC",
        "jetbot_rt.input_size": f"{image_size}x{image_size}",
        "jetbot_rt.color_order": "RGB",
        "jetbot_rt.pixel_range": "0-255",
        "jetbot_rt.action": ACTION_MEANING,
        "jetbot_rt.max_speed": repr(float(max_speed)),
        "jetbot_rt.task": task,
        "jetbot_rt.version": jetbot_rt.__version__,
    }


class _ExportedPolicy(nn.Module):
    """Same outputs as ``ActorCritic.forward``; wrapped so the graph's names are fixed here."""

    def __init__(self, model: ActorCritic) -> None:
        super().__init__()
        self.model = model

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.model(obs)


def export_model(
    model: ActorCritic,
    out: str | Path,
    *,
    task: str = "forward",
    max_speed: float = DEFAULT_MAX_SPEED,
    opset: int = DEFAULT_OPSET,
) -> float:
    """Write ``out`` and return the parity error; raise ``ExportError`` if it exceeds 1e-4."""
    if isinstance(opset, bool) or not isinstance(opset, int) or opset not in OPSETS:
        raise OptionError("opset", f"must be {OPSETS.start} .. {OPSETS.stop - 1}, got {opset!r}")
    out = Path(out)
    model = model.eval()
    for name, weight in model.state_dict().items():
        if not bool(torch.isfinite(weight).all()):
            raise ExportError(f"cannot export: weight {name} holds non-finite values (NaN or "
                              "infinity); the training diverged")
    size = model.config.image_size
    dummy = torch.rand(2, size, size, 3) * 255.0
    buffer = io.BytesIO()
    torch.onnx.export(
        _ExportedPolicy(model),
        (dummy,),
        buffer,
        dynamo=False,
        input_names=["obs"],
        output_names=["mu", "log_std", "value"],
        dynamic_axes={name: {0: "N"} for name in ("obs", "mu", "log_std", "value")},
        opset_version=opset,
    )
    proto = onnx.load_model_from_string(buffer.getvalue())
    onnx.helper.set_model_props(proto, policy_metadata(task, max_speed, size))
    onnx.checker.check_model(proto)
    data = proto.SerializeToString()
    error = parity_error(model, data)
    if not error < PARITY_TOLERANCE:  # NaN included: it compares false with everything
        raise ExportError(
            f"export parity check failed: onnxruntime vs torch max abs difference {error:.3g}"
            f" (must be < {PARITY_TOLERANCE})"
        )
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with safe_file.replaced_file(out.parent, out.name) as fd, \
                os.fdopen(os.dup(fd), "wb") as handle:
            handle.write(data)
    except OSError as exc:
        raise UsageError(f"cannot write {shown(out)}: {exc.strerror or exc}") from None
    return error


def weights_as_inputs(model: ActorCritic, opset: int = DEFAULT_OPSET) -> bytes:
    """The network as ONNX whose weights are inputs with defaults (onnxruntime's overridable
    initializers, named as in ``model.state_dict()``): one graph, fed new weights per call.
    Outputs ``mu_``, ``log_std_``, ``value_`` (an output may not share a weight's name)."""
    size = model.config.image_size
    buffer = io.BytesIO()
    torch.onnx.export(
        model.eval(),
        (torch.zeros(1, size, size, 3),),
        buffer,
        dynamo=False,
        input_names=["obs"],
        output_names=["mu_", "log_std_", "value_"],
        keep_initializers_as_inputs=True,
        do_constant_folding=False,  # folding would bake log_std.exp() and drop the weight
        opset_version=opset,
    )
    return buffer.getvalue()


def parity_error(model: ActorCritic, onnx_bytes: bytes, batch: int = 3, seed: int = 0) -> float:
    """Max abs difference over all outputs for random images, including the extremes 0/255."""
    rng = np.random.default_rng(seed)
    size = model.config.image_size
    images = rng.integers(0, 256, size=(batch, size, size, 3)).astype(np.float32)
    images[0] = 0.0
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(onnx_bytes, options, providers=["CPUExecutionProvider"])
    got = session.run(["mu", "log_std", "value"], {"obs": images})
    with torch.no_grad():
        want = [t.numpy() for t in model(torch.from_numpy(images))]
    differences = [np.abs(g - w).ravel() for g, w in zip(got, want, strict=True)]
    # One np.max over all outputs: it returns NaN if any output is NaN (non-finite outputs
    # on both sides differ by NaN), where Python's max() would keep whichever came first.
    return float(np.max(np.concatenate(differences)))


def export_checkpoint(checkpoint: str | Path, out: str | Path, opset: int = DEFAULT_OPSET) -> float:
    loaded = load_checkpoint(checkpoint)
    max_speed = DEFAULT_MAX_SPEED if loaded.max_speed is None else loaded.max_speed
    return export_model(loaded.model(), out, task=loaded.task, max_speed=max_speed, opset=opset)
