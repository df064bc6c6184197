"""Torch network -> ONNX file the runtime drives, with metadata that states how to feed it and a
parity check of onnxruntime against torch. ``export_model`` writes our ``ActorCritic`` in the
rl_games layout (``mu``, ``log_std``, ``value``); ``export_policy`` writes any user network
that maps an image batch to ``[N, 2]`` wheel commands. Both go through one writer."""

from __future__ import annotations

import io
import math
import numbers
import os
import stat
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import nn

import jetbot_rt
from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import shown
from jetbot_rt.config.sections import COLOR_ORDERS, LAYOUTS, PIXEL_RANGES
from jetbot_rt.errors import UsageError, first_line
from jetbot_rt.runtime.actions import DEFAULT_MAX_SPEED
from jetbot_rt.runtime.policy import CALIBRATED, DEADBAND_LIFT, MAX_INPUT_SIDE, META_PREFIX
from jetbot_rt.tasks import load_task
from jetbot_rt.train.checkpoint import load_checkpoint
from jetbot_rt.train.hyperparams import OptionError
from jetbot_rt.train.model import ActorCritic

DEFAULT_OPSET = 16
"""What the older onnxruntime builds on a Jetson run; newer ones read it too."""
OPSETS = range(8, 21)
"""The opsets torch's TorchScript exporter writes this network in (outside them it fails after
printing its graph); onnxruntime 1.x reads all of them."""
PARITY_TOLERANCE = 1e-4
ACTION_MEANING = "[left, right] wheel commands in [-1, 1]; duty = max_speed * clamp(mu, -1, 1)"
EXAMPLE_BATCH = 2
"""Images in the example the graph is traced with; the parity check feeds 3, so a network
that only works for the traced batch size is caught."""


class ExportError(UsageError):
    """The network cannot be a policy, or its export does not compute what it computes
    (exit 2, one line)."""


def policy_metadata(task: str | None, max_speed: float, image_size: int | tuple[int, int], *,
                    layout: str = "NHWC", color_order: str = "RGB",
                    pixel_range: str = "0-255", calibrated: bool = False) -> dict[str, str]:
    """The ``jetbot_rt.*`` keys ``jetbot_rt.runtime.policy`` reads; ``image_size`` is a side or
    ``(height, width)``; no ``task`` key when ``task`` is None. ``calibrated``: trained on a
    robot whose dead-band the runtime lifts (``[randomize] deadband_lift``), the key
    ``deadband_lift = "calibrated"``."""
    height, width = _size(image_size)
    metadata = {
        META_PREFIX + "layout": layout,
        META_PREFIX + "input_size": f"{width}x{height}",
        META_PREFIX + "color_order": color_order,
        META_PREFIX + "pixel_range": pixel_range,
        META_PREFIX + "action": ACTION_MEANING,
        META_PREFIX + "max_speed": repr(float(max_speed)),
        META_PREFIX + "task": task,
        META_PREFIX + DEADBAND_LIFT: CALIBRATED if calibrated else None,
        META_PREFIX + "version": jetbot_rt.__version__,
    }
    return {key: value for key, value in metadata.items() if value is not None}


def _size(image_size: int | tuple[int, int]) -> tuple[int, int]:
    return (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)


class _ExportedPolicy(nn.Module):
    """Same outputs as ``ActorCritic.forward``; wrapped so the graph's names are fixed here."""

    def __init__(self, model: ActorCritic) -> None:
        super().__init__()
        self.model = model

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.model(obs)


def _model_input(pixels: np.ndarray, layout: str, pixel_range: str) -> np.ndarray:
    """NHWC pixel values 0..255 as the runtime scales and lays them out for a model
    (``OnnxPolicy.prepare``; the colour order is irrelevant to random images)."""
    if pixel_range == "0-1":
        pixels = pixels * (1.0 / 255.0)
    elif pixel_range == "-1-1":
        pixels = pixels * (2.0 / 255.0) - 1.0
    if layout == "NCHW":
        pixels = pixels.transpose(0, 3, 1, 2)
    return np.ascontiguousarray(pixels, dtype=np.float32)


def _outputs(result: object) -> list[torch.Tensor]:
    """A network's outputs as a list: one tensor, or a tuple or list of them."""
    items = list(result) if isinstance(result, (tuple, list)) else [result]
    if not items or not all(isinstance(item, torch.Tensor) for item in items):
        raise ExportError("cannot export: the network must return a tensor (or a tuple of "
                          f"tensors, the first one the actions), it returned "
                          f"{type(result).__name__}")
    return items


def _device(model: nn.Module) -> torch.device:
    first = next(iter(model.parameters()), None)
    return first.device if first is not None else torch.device("cpu")


def _write_policy(
    model: nn.Module,
    out: str | Path,
    *,
    output_names: Sequence[str],
    metadata: dict[str, str],
    opset: int,
) -> float:
    """Trace ``model`` with the TorchScript exporter (``dynamo=False``: the dynamo exporter,
    recent torch's default, needs onnxscript, which no extra installs) into ONNX input ``obs``
    with a free batch dimension, set ``metadata``, check parity, and replace ``out`` only if
    it passes. Returns the parity error."""
    if isinstance(opset, bool) or not isinstance(opset, int) or opset not in OPSETS:
        raise OptionError("opset", f"must be {OPSETS.start} .. {OPSETS.stop - 1}, got {opset!r}")
    out = Path(out)
    width, height = (int(side) for side in metadata[META_PREFIX + "input_size"].split("x"))
    layout = metadata[META_PREFIX + "layout"]
    pixels = (torch.rand(EXAMPLE_BATCH, height, width, 3) * 255.0).numpy()
    dummy = torch.from_numpy(_model_input(pixels, layout, metadata[META_PREFIX + "pixel_range"]))
    dummy = dummy.to(_device(model))
    buffer = io.BytesIO()
    torch.onnx.export(
        model,
        (dummy,),
        buffer,
        dynamo=False,
        input_names=["obs"],
        output_names=list(output_names),
        dynamic_axes={name: {0: "N"} for name in ("obs", *output_names)},
        opset_version=opset,
    )
    proto = onnx.load_model_from_string(buffer.getvalue())
    onnx.helper.set_model_props(proto, metadata)
    onnx.checker.check_model(proto)
    data = proto.SerializeToString()
    error = parity_error(model, data)
    if not error < PARITY_TOLERANCE:  # NaN included: it compares false with everything
        raise ExportError(
            f"export parity check failed: onnxruntime vs torch max difference {error:.3g}"
            f" (absolute, relative above 1; must be < {PARITY_TOLERANCE})"
            + ("; an output is NaN or infinite" if math.isnan(error) else "")
        )
    write_model(out, data)
    return error


def write_model(out: Path, data: bytes) -> None:
    """Replace ``out`` with ``data`` whole (a link planted there is replaced, not followed;
    a device, FIFO or socket there is refused: a rename would replace it, ``/dev/null``
    included); a failure is a one-line ``UsageError``."""
    try:
        mode = os.lstat(out).st_mode if os.path.lexists(out) else None
        if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
            raise UsageError(f"cannot write {shown(out)}: not a regular file (refused: "
                             "writing would replace it)")
        out.parent.mkdir(parents=True, exist_ok=True)
        with safe_file.replaced_file(out.parent, out.name) as fd, \
                os.fdopen(os.dup(fd), "wb") as handle:
            handle.write(data)
    except OSError as exc:
        raise UsageError(f"cannot write {shown(out)}: {exc.strerror or exc}") from None


def _check_weights(model: nn.Module) -> None:
    for name, weight in model.state_dict().items():
        if not bool(torch.isfinite(weight).all()):
            raise ExportError(f"cannot export: weight {name} holds non-finite values (NaN or "
                              "infinity); the training diverged")


def _in_eval_mode(model: nn.Module, export: Callable[[], float]) -> float:
    """Run ``export()`` with ``model`` in eval mode (dropout off, batch norm's running
    statistics), then give it back in the mode it came in."""
    was_training = model.training
    model.eval()
    try:
        return export()
    finally:
        model.train(was_training)


def export_model(
    model: ActorCritic,
    out: str | Path,
    *,
    task: str = "forward",
    max_speed: float = DEFAULT_MAX_SPEED,
    opset: int = DEFAULT_OPSET,
    calibrated: bool = False,
) -> float:
    """Write ``out`` and return the parity error; raise ``ExportError`` if it exceeds 1e-4."""
    _check_weights(model)
    metadata = policy_metadata(task, max_speed, model.config.image_size, calibrated=calibrated)
    return _in_eval_mode(model, lambda: _write_policy(
        _ExportedPolicy(model), out, output_names=("mu", "log_std", "value"),
        metadata=metadata, opset=opset))


def export_policy(
    model: nn.Module,
    path: str | Path,
    *,
    image_size: int | tuple[int, int] = 56,
    layout: str = "NHWC",
    color_order: str = "RGB",
    pixel_range: str = "0-255",
    max_speed: float | None = None,
    task: str | None = "forward",
    opset: int = DEFAULT_OPSET,
) -> float:
    """Write a user's network as an ONNX policy that ``jetbot-rt run --policy`` drives.

    ``model`` maps a float32 image batch -- ``[N, H, W, 3]`` (``layout="NHWC"``) or
    ``[N, 3, H, W]`` (``"NCHW"``), RGB or BGR, pixel values scaled to ``pixel_range`` --
    to ``[N, 2]`` wheel commands ``[left, right]`` in [-1, 1] (or a tuple whose first item
    is that). ``image_size``: a side, or ``(height, width)``. ``max_speed``: the duty at
    ``|mu| = 1``, default the task's (0.1 forward, 0.5 seek). ``task``: the sim scene
    ``jetbot-rt run --backend sim`` builds for it; None writes no task. Returns the parity
    error (onnxruntime vs torch); raises ``ExportError`` (nothing written) if it is 1e-4 or
    more, NaN included, and ``OptionError`` for a bad argument."""
    if not isinstance(model, nn.Module):
        raise OptionError("model", f"must be a torch.nn.Module, got {type(model).__name__}")
    height, width = _checked_size(image_size)
    for name, value, allowed in (("layout", layout, LAYOUTS),
                                 ("color_order", color_order, COLOR_ORDERS),
                                 ("pixel_range", pixel_range, PIXEL_RANGES)):
        if value not in allowed:
            raise OptionError(name, f"must be one of {', '.join(allowed)}, got {value!r}")
    try:
        loaded = load_task(task) if task is not None else None
    except UsageError as exc:
        raise OptionError("task", f"must be a task or None: {exc}") from None
    if max_speed is None:
        max_speed = loaded.max_speed if loaded is not None else DEFAULT_MAX_SPEED
    if (isinstance(max_speed, bool) or not isinstance(max_speed, numbers.Real)
            or not 0.0 < max_speed <= 1.0):
        raise OptionError("max_speed", f"must be a number in (0, 1], got {max_speed!r}")
    metadata = policy_metadata(task, max_speed, (height, width), layout=layout,
                               color_order=color_order, pixel_range=pixel_range)

    def export() -> float:
        with torch.no_grad():
            pixels = np.zeros((EXAMPLE_BATCH, height, width, 3), np.float32)
            example = torch.from_numpy(_model_input(pixels, layout, pixel_range))
            outputs = _outputs(model(example.to(_device(model))))
        if not outputs[0].is_floating_point():
            raise ExportError(f"cannot export: the network's actions are {outputs[0].dtype}; "
                              "the runtime needs floating-point [left, right] commands")
        if tuple(outputs[0].shape) != (EXAMPLE_BATCH, 2):
            raise ExportError(f"cannot export: for a batch of {EXAMPLE_BATCH} images the "
                              f"network's actions have shape {list(outputs[0].shape)}; the "
                              "runtime needs [N, 2], [left, right] per image")
        _check_weights(model)  # after a first call, which gives lazy layers their weights
        names = ["mu"] + [f"output_{i}" for i in range(1, len(outputs))]
        return _write_policy(model, path, output_names=names, metadata=metadata, opset=opset)

    return _in_eval_mode(model, export)


def _checked_size(image_size: int | tuple[int, int]) -> tuple[int, int]:
    sides = list(image_size) if isinstance(image_size, (tuple, list)) else [image_size]
    if len(sides) not in (1, 2) or not all(
            isinstance(s, numbers.Integral) and not isinstance(s, bool)
            and 1 <= s <= MAX_INPUT_SIDE for s in sides):
        raise OptionError("image_size", f"must be a side or (height, width), each 1 .. "
                                        f"{MAX_INPUT_SIDE} pixels, got {image_size!r}")
    return int(sides[0]), int(sides[-1])


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


def parity_error(model: nn.Module, onnx_bytes: bytes, batch: int = 3, seed: int = 0) -> float:
    """Max difference over all outputs, absolute up to 1 and relative above (to torch's value),
    for random images (an all-black one among them) fed as the runtime feeds them: at the
    graph's input size, in the layout and pixel range its ``jetbot_rt.*`` metadata states
    (NHWC, 0..255 without)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.log_severity_level = 4  # a failed run reaches the user through ExportError
    session = ort.InferenceSession(onnx_bytes, options, providers=["CPUExecutionProvider"])
    metadata = session.get_modelmeta().custom_metadata_map
    layout = metadata.get(META_PREFIX + "layout", "NHWC")
    model_input = session.get_inputs()[0]
    shape = model_input.shape
    if isinstance(shape[0], int):
        batch = shape[0]
    height, width = shape[1:3] if layout == "NHWC" else shape[2:4]
    pixels = np.random.default_rng(seed).integers(0, 256, size=(batch, height, width, 3))
    pixels = pixels.astype(np.float32)
    pixels[0] = 0.0
    images = _model_input(pixels, layout, metadata.get(META_PREFIX + "pixel_range", "0-255"))
    try:
        got = session.run(None, {model_input.name: images})
    except Exception as exc:  # onnxruntime raises several unrelated types
        raise ExportError(f"export parity check failed: onnxruntime cannot run the graph on "
                          f"a batch of {batch} images (a batch size fixed in the network, such "
                          f"as reshape(2, -1)? {first_line(exc)})") from None
    # TF32 off: a GPU's default TF32 convolutions differ from float32 by ~3e-4 (measured on
    # an H200), which would refuse a correct graph trained there.
    cudnn = torch.backends.cudnn
    with torch.no_grad(), cudnn.flags(enabled=cudnn.enabled, benchmark=cudnn.benchmark,
                                      deterministic=cudnn.deterministic, allow_tf32=False):
        result = model(torch.from_numpy(images).to(_device(model)))
    want = [t.detach().cpu().numpy() for t in _outputs(result)]
    if [g.shape for g in got] != [w.shape for w in want]:
        raise ExportError(f"export parity check failed: output shapes differ, onnxruntime "
                          f"{[g.shape for g in got]} vs torch {[w.shape for w in want]}")
    # Relative above 1: float32 rounding grows with the values (a linear layer on raw 0..255
    # pixels gives outputs in the hundreds), and a correct graph must not be refused for it.
    with np.errstate(invalid="ignore", divide="ignore"):  # inf vs inf: NaN, refused below
        differences = [(np.abs(g - w) / np.maximum(1.0, np.abs(w))).ravel()
                       for g, w in zip(got, want, strict=True)]
    # One np.max over all outputs: it returns NaN if any output is NaN (non-finite outputs
    # on both sides differ by NaN), where Python's max() would keep whichever came first.
    return float(np.max(np.concatenate(differences)))


def export_checkpoint(checkpoint: str | Path, out: str | Path, opset: int = DEFAULT_OPSET) -> float:
    loaded = load_checkpoint(checkpoint)
    max_speed = DEFAULT_MAX_SPEED if loaded.max_speed is None else loaded.max_speed
    return export_model(loaded.model(), out, task=loaded.task, max_speed=max_speed, opset=opset,
                        calibrated=loaded.calibrated)
