"""An ONNX image policy: reads what the model expects and prepares camera frames to match.

The model's input name, layout, size and dtype come from the graph; colour order, pixel range
and ``max_speed`` from the metadata our exporter writes (``jetbot_rt.*`` keys). Models without
metadata get the rl_games/Isaac Lab defaults: NHWC, RGB, float32, values 0..255.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import shown
from jetbot_rt.config.sections import LAYOUTS, Config, PolicyConfig
from jetbot_rt.errors import Fault, UsageError, first_line

META_PREFIX = "jetbot_rt."
DEADBAND_LIFT = "deadband_lift"
CALIBRATED = "calibrated"
"""``jetbot_rt.deadband_lift = "calibrated"``: a policy trained on a robot whose dead-band
the runtime lifts (``[randomize] deadband_lift``), that expects ``[actions] deadband``."""


def trained_calibrated(metadata: dict[str, str]) -> bool:
    """Whether a model's metadata says it was trained on a robot whose dead-band is lifted."""
    return metadata.get(META_PREFIX + DEADBAND_LIFT) == CALIBRATED


PROVIDER_PREFERENCE = (
    "TensorrtExecutionProvider",
    "CUDAExecutionProvider",
    "CPUExecutionProvider",
)
_DTYPES = {
    "tensor(float)": np.float32,
    "tensor(float16)": np.float16,
    "tensor(uint8)": np.uint8,
}


def tensorrt_cache_dir() -> Path:
    """Where TensorRT engines are kept between starts (the service's HOME is its state dir)."""
    return Path(os.environ.get("JETBOT_RT_CACHE_DIR") or Path.home() / ".cache" / "jetbot_rt")


def provider_options(providers: list[str]) -> list[str | tuple[str, dict[str, str]]]:
    """TensorRT builds an engine on the first inference (minutes on a Jetson); caching it
    makes every later start take seconds."""
    result: list[str | tuple[str, dict[str, str]]] = []
    for name in providers:
        if name == "TensorrtExecutionProvider":
            cache = tensorrt_cache_dir() / "tensorrt"
            result.append((name, {"trt_engine_cache_enable": "True",
                                  "trt_engine_cache_path": str(cache)}))
        else:
            result.append(name)
    return result


MAX_MODEL_BYTES = 2 * 1024**3
"""protobuf's own limit (2 GiB): no ONNX file (without external data) is larger."""
MAX_INPUT_SIDE = 4096
"""The largest input width or height a policy may declare. The largest sensor a JetBot
carries (IMX219) gives 3280x2464; every frame of the policy's size is allocated several
times over (the camera pipe's W*H*3 bytes, a float32 tensor four times that, ``[record]
queue_frames`` slots of shared memory), so a declared 20000x20000 (1.2 GB per frame, 4.8 GB as
float) or 2**31 would end in a failed allocation while starting, a fault, not a refusal."""


def _model_source(path: Path) -> str | bytes:
    """What onnxruntime is given: the path, or the file's bytes where the path is not UTF-8
    (onnxruntime accepts only UTF-8 paths and says "incompatible constructor arguments").
    Either way the file is first opened as ``safe_file`` does: a FIFO or a device is refused
    without blocking."""
    fd = safe_file.open_regular(path, "policy")
    size = os.fstat(fd).st_size
    os.close(fd)
    if size > MAX_MODEL_BYTES:
        raise UsageError(f"policy {shown(path)} is larger than 2 GiB: not an ONNX model")
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        return safe_file.read_bytes(path, "policy", MAX_MODEL_BYTES)
    return str(path)


DEFAULT_TASK = "forward"
"""The task whose bundled policy ``jetbot-rt run`` drives without ``--policy``."""


def bundled_policy_path(task: str = DEFAULT_TASK) -> Path:
    """The policy bundled in the package for ``task`` (``policies/<task>.onnx``)."""
    return Path(__file__).resolve().parents[1] / "policies" / f"{task}.onnx"


def bundled_task(config: Config) -> str:
    """The task whose bundled policy a run without ``--policy`` drives: ``[sim] task`` where
    one is bundled for it (``jetbot-rt run --backend sim`` with ``[sim] task = "seek"`` drives
    the seek policy in the seek scene), else forward, the default task."""
    task = config.sim.task  # a plain name only: a path or FILE:Class bundles nothing
    return task if task and task.isidentifier() and bundled_policy_path(task).is_file() \
        else DEFAULT_TASK


def resolve_policy_path(given: str | Path | None, task: str = DEFAULT_TASK) -> Path:
    """The policy a command uses: ``given`` (a flag or ``[policy] path``), else the one
    bundled for ``task``; ``UsageError`` when none is given and none is bundled."""
    if given:
        return Path(given)
    bundled = bundled_policy_path(task)
    if not bundled.is_file():
        raise UsageError(f"no bundled {task} policy in this installation; "
                         "pass --policy FILE.onnx")
    return bundled


@dataclass(frozen=True)
class InputSpec:
    """How a frame must look when it reaches the model."""

    name: str
    layout: str  # NHWC or NCHW
    width: int
    height: int
    dtype: Any
    color_order: str  # RGB or BGR
    pixel_range: str  # 0-255, 0-1 or -1-1
    clip: float | None = None  # then values are clipped to [-clip, clip]


def _dim(value: Any) -> int | None:
    return value if isinstance(value, int) and value > 0 else None


def _infer_layout(shape: list[Any]) -> str | None:
    if _dim(shape[3]) == 3 and _dim(shape[1]) != 3:
        return "NHWC"
    if _dim(shape[1]) == 3 and _dim(shape[3]) != 3:
        return "NCHW"
    if _dim(shape[3]) == 3:  # 3x?x3: ambiguous, NHWC is what rl_games exported
        return "NHWC"
    return None


QUOTED_CHARS = 40
"""A metadata value in a message is cut to this many characters: the model says what it
likes, the message stays one readable line."""


def quoted(text: str) -> str:
    """``text`` as a message quotes it: ``repr``, cut at ``QUOTED_CHARS`` with ``...``."""
    return repr(text[:QUOTED_CHARS]) + ("..." if len(text) > QUOTED_CHARS else "")


def check_max_speed(path: str, metadata: dict[str, str]) -> None:
    """``jetbot_rt.max_speed``, when the model states one, is a number in (0, 1]: what our
    exporter writes. Anything else is a broken export, refused rather than replaced by the
    default without a word."""
    stated = metadata.get(META_PREFIX + "max_speed")
    if stated is None:
        return
    try:
        value = float(stated)
    except ValueError:
        value = math.nan
    if not 0.0 < value <= 1.0:  # NaN fails too
        raise UsageError(f"policy {path}: its metadata {META_PREFIX}max_speed = {quoted(stated)} "
                         "is not a number in (0, 1] (fix the export)")


class OnnxPolicy:
    """``infer(image)`` maps one HxWx3 uint8 RGB frame to ``mu``: two floats, ``[left, right]``."""

    def __init__(self, session: Any, spec: InputSpec, action_output: str, path: Path,
                 metadata: dict[str, str]) -> None:
        self.session = session
        self.spec = spec
        self.action_output = action_output
        self.path = path
        self.metadata = metadata

    @property
    def max_speed(self) -> float | None:
        """The model's ``max_speed`` metadata (checked by ``load``), or None."""
        stated = self.metadata.get(META_PREFIX + "max_speed")
        return None if stated is None else float(stated)

    @property
    def calibrated(self) -> bool:
        """Trained on a robot whose dead-band ``[actions] deadband`` lifts."""
        return trained_calibrated(self.metadata)

    @property
    def providers(self) -> list[str]:
        return list(self.session.get_providers())

    @classmethod
    def load(cls, path: str | Path, config: PolicyConfig | None = None,
             threads: int | None = None) -> OnnxPolicy:
        """Open and validate the model; every problem is a ``UsageError`` naming the file.
        ``threads`` overrides ``config.threads``, onnxruntime's CPU threads."""
        import onnxruntime as ort

        config = config or PolicyConfig()
        path = Path(path)
        if not os.path.lexists(path):
            raise UsageError(f"policy {shown(path)}: no such file")
        source = _model_source(path)
        available = ort.get_available_providers()
        wanted = config.providers or list(PROVIDER_PREFERENCE)
        providers = [p for p in wanted if p in available] or ["CPUExecutionProvider"]
        options = ort.SessionOptions()
        options.log_severity_level = 4  # errors reach the user through our own message
        # onnxruntime's worker threads busy-wait after each run by default: at 30 Hz that
        # burns a core between ticks (43 % of one here for a 0.2 ms model) that the camera,
        # the sim or the Jetson's power budget need.
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        options.add_session_config_entry("session.inter_op.allow_spinning", "0")
        threads = threads if threads is not None else config.threads
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = threads
        try:
            session = ort.InferenceSession(
                source, options, providers=provider_options(providers)
            )
        except Exception as exc:  # onnxruntime raises several unrelated types for bad files
            raise UsageError(
                f"policy {shown(path)}: not a loadable ONNX model ({first_line(exc)})"
            ) from None
        try:  # onnxruntime hands text over as UTF-8, which the file need not be
            metadata = dict(session.get_modelmeta().custom_metadata_map)
            spec = cls.input_spec(session, shown(path), config, metadata)
            action_output = cls.action_output_of(session, shown(path))
        except UnicodeDecodeError:
            raise UsageError(f"policy {shown(path)}: its metadata or input and output names "
                             "are not UTF-8 text") from None
        check_max_speed(shown(path), metadata)
        return cls(session, spec, action_output, path, metadata)

    @staticmethod
    def input_spec(session: Any, path: str, config: PolicyConfig,
                   metadata: dict[str, str]) -> InputSpec:
        inputs = session.get_inputs()
        if len(inputs) != 1:
            names = ", ".join(i.name for i in inputs)
            raise UsageError(
                f"policy {path}: expected one image input, found {len(inputs)} ({names})"
            )
        model_input = inputs[0]
        shape = list(model_input.shape)
        if len(shape) != 4:
            raise UsageError(
                f"policy {path}: expected an image input [N,H,W,3] or [N,3,H,W], "
                f"found {model_input.name} with shape {shape}"
            )
        if model_input.type not in _DTYPES:
            raise UsageError(
                f"policy {path}: expected input dtype float32, float16 or uint8, "
                f"found {model_input.type}"
            )
        stated = metadata.get(META_PREFIX + "layout")
        if not config.layout and stated is not None and stated not in LAYOUTS:
            raise UsageError(
                f"policy {path}: its metadata {META_PREFIX}layout = {quoted(stated)} is not one of "
                f"{', '.join(LAYOUTS)} (fix the export, or set [policy] layout to override it)"
            )
        layout = config.layout or stated or _infer_layout(shape)
        if layout not in LAYOUTS:
            raise UsageError(
                f"policy {path}: cannot tell the image layout of input shape {shape} "
                "(set [policy] layout)"
            )
        channels, height, width = (
            (shape[3], shape[1], shape[2]) if layout == "NHWC" else (shape[1], shape[2], shape[3])
        )
        if _dim(channels) != 3:
            raise UsageError(
                f"policy {path}: expected 3 colour channels in {layout} input, found shape {shape}"
            )
        if _dim(height) is None or _dim(width) is None:
            raise UsageError(f"policy {path}: input {model_input.name} has no fixed size: {shape}")
        if max(width, height) > MAX_INPUT_SIDE:
            raise UsageError(f"policy {path}: input {model_input.name} is {width}x{height}; "
                             f"the runtime takes at most {MAX_INPUT_SIDE} pixels a side")
        declared = metadata.get(META_PREFIX + "input_size")
        if declared is not None and declared != f"{width}x{height}":
            raise UsageError(f"policy {path}: metadata says input size {quoted(declared)}, "
                             f"the graph's input {model_input.name} is {width}x{height}")
        color = config.color_order or metadata.get(META_PREFIX + "color_order", "RGB")
        pixel_range = config.pixel_range or metadata.get(META_PREFIX + "pixel_range", "0-255")
        if color not in ("RGB", "BGR") or pixel_range not in ("0-255", "0-1", "-1-1"):
            raise UsageError(
                f"policy {path}: unsupported metadata color_order={quoted(color)} "
                f"pixel_range={quoted(pixel_range)}"
            )
        if config.clip is not None and _DTYPES[model_input.type] == np.uint8:
            raise UsageError(f"policy {path}: [policy] clip needs a float input, "
                             f"{model_input.name} is uint8")
        return InputSpec(model_input.name, layout, int(width), int(height),
                         _DTYPES[model_input.type], color, pixel_range, config.clip)

    @staticmethod
    def action_output_of(session: Any, path: str) -> str:
        outputs = session.get_outputs()
        chosen = next((o for o in outputs if o.name == "mu"), outputs[0])
        if chosen.type not in ("tensor(float)", "tensor(float16)", "tensor(double)"):
            raise UsageError(f"policy {path}: expected float actions in output {chosen.name}, "
                             f"found {chosen.type}")
        # [N, 2] with a symbolic batch N (our exporter's) or [1, 2]; [2] for a bare vector
        action_dims = chosen.shape[1:] if len(chosen.shape) >= 2 else chosen.shape
        fixed = all(isinstance(d, int) for d in action_dims)
        if fixed and int(np.prod(action_dims)) != 2:
            raise UsageError(f"policy {path}: expected 2 actions [left, right] in output "
                             f"{chosen.name}, found shape {chosen.shape}")
        return chosen.name

    def fit(self, image: np.ndarray) -> np.ndarray:
        """The frame at the model's input size (unchanged if it is already): what a recording
        keeps, before colour order, dtype and layout are applied."""
        spec = self.spec
        if image.shape[0] != spec.height or image.shape[1] != spec.width:
            image = cv2.resize(image, (spec.width, spec.height), interpolation=cv2.INTER_AREA)
        return image

    def prepare(self, image: np.ndarray) -> np.ndarray:
        """HxWx3 uint8 RGB -> the batch of one the model takes."""
        spec = self.spec
        if image.ndim != 3 or image.shape[2] != 3:
            raise Fault(f"camera frame has shape {image.shape}, expected HxWx3")
        image = self.fit(image)
        if spec.color_order == "BGR":
            image = image[:, :, ::-1]
        if spec.dtype == np.uint8:
            tensor = np.ascontiguousarray(image)
        else:
            tensor = image.astype(np.float32)
            if spec.pixel_range == "0-1":
                tensor *= 1.0 / 255.0
            elif spec.pixel_range == "-1-1":
                tensor = tensor * (2.0 / 255.0) - 1.0
            if spec.clip is not None:
                np.clip(tensor, -spec.clip, spec.clip, out=tensor)
            tensor = tensor.astype(spec.dtype, copy=False)
        if spec.layout == "NCHW":
            tensor = tensor.transpose(2, 0, 1)
        return np.ascontiguousarray(tensor[None])

    def infer(self, image: np.ndarray) -> np.ndarray:
        """One forward pass; returns ``mu`` as float64 ``[left, right]``."""
        feed = {self.spec.name: self.prepare(image)}
        try:
            (output,) = self.session.run([self.action_output], feed)
        except Exception as exc:  # onnxruntime's errors while running are faults, not usage
            raise Fault(f"policy inference failed: {first_line(exc)}") from None
        mu = np.asarray(output, dtype=np.float64).reshape(-1)
        if mu.size != 2:
            raise Fault(f"policy gave {mu.size} action values, expected 2")
        return mu

    def describe(self) -> dict[str, Any]:
        spec = self.spec
        return {
            "path": shown(self.path),
            "input": spec.name,
            "layout": spec.layout,
            "size": [spec.width, spec.height],
            "dtype": np.dtype(spec.dtype).name,
            "color_order": spec.color_order,
            "pixel_range": spec.pixel_range,
            "clip": spec.clip,
            "action_output": self.action_output,
            "max_speed": self.max_speed,
            "providers": self.providers,
        }
