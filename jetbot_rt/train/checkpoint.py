"""Trainer checkpoints: written by the trainers, read back as untrusted input.

A checkpoint is one ``torch.save`` dict with a format tag. Whoever hands one to ``export``,
``train --init`` or ``train --resume`` may hand a file of any kind, so every defect is one
``UsageError`` naming the file (exit 2), never a traceback or a hang:

- the file is read by ``safe_file`` (a regular file, opened without blocking, at most
  ``MAX_CHECKPOINT_BYTES``);
- it must be a zip archive whose entries are stored uncompressed, as ``torch.save`` writes
  them: a compressed entry could expand a small file to any size, and torch's older
  non-zip format reads sizes from the file before it allocates;
- it is unpickled with ``weights_only=True`` (tensors, numbers, strings and containers; no
  code runs);
- every field is checked for type and range before it is used: the network's weights must
  have exactly the names and shapes its model config gives and be finite, the optimizer's
  state likewise, the counters non-negative integers.
"""

from __future__ import annotations

import io
import math
import os
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import shown
from jetbot_rt.errors import UsageError, first_line
from jetbot_rt.tasks import available
from jetbot_rt.tasks.loader import is_code_reference
from jetbot_rt.train.hyperparams import (
    MAX_PARAMETERS,
    CriticConfig,
    ModelConfig,
    OptionError,
    value_text,
)
from jetbot_rt.train.model import ActorCritic

CHECKPOINT_FORMAT = "jetbot_rt.ppo/1"
CHECKPOINT_NAME = "checkpoint.pt"
MAX_TASK_NAME = 4096
"""Characters of a checkpoint's task name (a built-in's, or FILE.py:Class)."""
MAX_CHECKPOINT_BYTES = 128 * safe_file.MIB
"""The largest network the trainer builds (``args.MAX_PARAMETERS``, 32 MB of float32) with
Adam's two moments is 96 MB; anything larger is not one of ours."""
ALGOS = ("ppo", "dagger")
MAX_COUNT = 2**62
"""Step and update counters above this are not counts (and would overflow torch's int64)."""


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write atomically under a fresh name, then rename: a run killed mid-save leaves the
    previous checkpoint intact, and a link planted at ``path`` is replaced, not followed."""
    with safe_file.replaced_file(path.parent, path.name) as fd, \
            os.fdopen(os.dup(fd), "wb") as handle:
        torch.save({"format": CHECKPOINT_FORMAT, **state}, handle)


class _Defect(Exception):
    """A field of a checkpoint that is wrong; ``load_checkpoint`` names the file."""


def _count(state: dict[str, Any], key: str) -> int:
    value = state.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_COUNT:
        raise _Defect(f"{key} must be an integer >= 0, got {value_text(value)}")
    return value


def _number(state: dict[str, Any], key: str, low: float, high: float = math.inf) -> float:
    value = state.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not (math.isfinite(value) and low <= value <= high):
        raise _Defect(f"{key} must be a number in [{low:g}, {high:g}], got {value_text(value)}")
    return float(value)


def _check_tensor(name: str, value: Any, like: torch.Tensor) -> torch.Tensor:
    """``value`` is a dense float tensor of ``like``'s dtype and shape, every element finite.
    The shape is checked first: a crafted view can claim any size over a one-element storage,
    and only then is it read."""
    if not isinstance(value, torch.Tensor):
        raise _Defect(f"{name} must be a tensor, got {value_text(value)}")
    if value.layout != torch.strided or value.is_quantized or value.dtype != like.dtype:
        raise _Defect(f"{name} must be a dense {like.dtype} tensor, got {value.dtype} "
                      f"({value.layout})")
    if value.shape != like.shape:
        raise _Defect(f"{name} has shape {list(value.shape)}, expected {list(like.shape)} "
                      "(from the model config)")
    if not bool(torch.isfinite(value).all()):
        raise _Defect(f"{name} holds non-finite values (NaN or infinity)")
    return value


@dataclass(frozen=True)
class TrainingState:
    """What ``--resume`` continues from, beside the network."""

    path: str
    """The checkpoint, as messages show it."""
    global_step: int
    update: int
    """Updates (PPO) or iterations (DAgger) done."""
    wall_s: float
    optimizer: dict[str, Any]
    """Adam's ``state_dict`` as saved; checked by ``load_optimizer``."""
    reward_rms: dict[str, float] | None
    """PPO's reward normaliser: ``mean``, ``var``, ``count``."""

    def load_optimizer(self, optimizer: torch.optim.Optimizer) -> None:
        """Load the saved Adam state into ``optimizer`` (built over the checkpoint's network
        with the trainer's own settings) after checking that it fits: one parameter group
        with the same settings (the learning rate excepted: the trainers set it every
        update) and, per parameter, finite moments of its shape."""
        try:
            _check_optimizer(self.optimizer, optimizer)
        except _Defect as exc:
            raise UsageError(f"checkpoint {self.path}: optimizer {exc}") from None
        optimizer.load_state_dict(self.optimizer)


@dataclass(frozen=True)
class Checkpoint:
    """A checkpoint read and checked by ``load_checkpoint``."""

    path: str
    """The file, as messages show it."""
    task: str
    algo: str
    model_config: ModelConfig
    weights: dict[str, Any]
    """Checked against the network in ``model()``, where its shapes are known."""
    max_speed: float | None
    training: TrainingState | None
    """None for a checkpoint without an optimizer (a network only: export, ``--init``)."""
    critic: CriticConfig | None = None
    """The asymmetric critic of a ``--critic state`` run (its weights are ``critic.*``);
    None: the value is the image head's."""
    calibrated: bool = False
    """Trained on a robot whose dead-band the runtime lifts (``[randomize] deadband_lift``):
    its export says so (``jetbot_rt.deadband_lift``)."""

    def _refuse(self, problem: str) -> UsageError:
        return UsageError(f"checkpoint {self.path}: {problem}")

    def model(self) -> ActorCritic:
        """The network with the checkpoint's weights (its critic's too), in eval mode."""
        model = ActorCritic(self.model_config, self.critic)
        expected = model.state_dict()
        missing = sorted(set(expected) - set(self.weights))
        extra = sorted(str(k) for k in self.weights if k not in expected)
        if missing or extra:
            what = (f"lacks weight(s) {', '.join(missing[:3])}" if missing else
                    f"has weight(s) the network has not: {', '.join(extra[:3])}")
            raise self._refuse(f"model {what}")
        try:
            for name, like in expected.items():
                _check_tensor(f"model weight {name}", self.weights[name], like)
        except _Defect as exc:
            raise self._refuse(str(exc)) from None
        model.load_state_dict(self.weights)
        return model.eval()

    def check_resumable(self, task: str, algo: str,
                        critic: CriticConfig | None = None) -> TrainingState:
        """The training state, if this checkpoint can continue a run of ``algo`` on ``task``
        with ``critic`` (None: the image critic; a critic of another kind or width is
        refused, its hidden width is the checkpoint's, as the rest of its network)."""
        if self.task != task:
            raise self._refuse(f"is for task {self.task!r}, not {task!r}")
        if self.algo != algo:
            raise self._refuse(f"was written by {self.algo}, not {algo} (a new run can start "
                               "from its network: init)")
        if (self.critic is None) != (critic is None):
            was, now = ("state", "image") if critic is None else ("image", "state")
            raise self._refuse(f"was trained with --critic {was}, not --critic {now}: resume "
                               f"it with --critic {was} (a new run can start from its actor: "
                               "--init)")
        if self.critic is not None and critic is not None and \
                self.critic.state_size != critic.state_size:
            raise self._refuse(f"its critic reads {self.critic.state_size} state values, task "
                               f"{task!r} gives {critic.state_size}")
        if self.critic is not None and critic is not None and \
                self.critic.predicts_state != critic.predicts_state:
            was, now = ("with", "without") if self.critic.predicts_state else ("without", "with")
            raise self._refuse(f"was trained {was} --predict-state, not {now}: resume it as it "
                               "was trained (a new run can start from its network: --init)")
        if self.training is None:
            raise self._refuse("holds no optimizer state to resume from (a new run can start "
                               "from its network: init)")
        return self.training


def _check_optimizer(saved: Any, optimizer: torch.optim.Optimizer) -> None:
    fresh = optimizer.state_dict()
    if not isinstance(saved, dict) or set(saved) != {"state", "param_groups"}:
        raise _Defect("must be a dict of state and param_groups")
    groups = saved["param_groups"]
    if not isinstance(groups, list) or len(groups) != len(fresh["param_groups"]):
        raise _Defect(f"must have {len(fresh['param_groups'])} parameter group(s)")
    params = [p for group in optimizer.param_groups for p in group["params"]]
    for group, own in zip(groups, fresh["param_groups"], strict=True):
        if not isinstance(group, dict):
            raise _Defect("parameter group must be a dict")
        missing = sorted({"params", "lr", "betas", "eps", "weight_decay"} - set(group))
        unknown = sorted(str(key) for key in group if key not in own)
        if missing or unknown:
            raise _Defect(f"parameter group lacks {', '.join(missing)}" if missing else
                          f"parameter group has settings Adam has not: {', '.join(unknown[:3])}")
        if _plain(group["params"]) != own["params"]:
            raise _Defect(f"parameter group must list parameters {own['params']}")
        _number(group, "lr", 0.0)
        for key, value in group.items():
            if key not in ("params", "lr") and _plain(value) != _plain(own[key]):
                raise _Defect(f"{key} is {value_text(value)}, this trainer uses {own[key]!r}")
    state = saved["state"]
    if not isinstance(state, dict):
        raise _Defect("state must be a dict")
    for index, entry in state.items():
        if isinstance(index, bool) or not isinstance(index, int) or \
                not 0 <= index < len(params):
            raise _Defect(f"state names parameter {value_text(index)}, the network has "
                          f"{len(params)}")
        if not isinstance(entry, dict) or set(entry) != {"step", "exp_avg", "exp_avg_sq"}:
            raise _Defect(f"state of parameter {index} must hold step, exp_avg, exp_avg_sq")
        step = entry["step"]
        if not (isinstance(step, torch.Tensor) and step.layout == torch.strided
                and step.dim() == 0 and step.is_floating_point()
                and bool(torch.isfinite(step)) and float(step) >= 0):
            raise _Defect(f"step of parameter {index} must be a finite scalar tensor >= 0")
        like = params[index].detach()
        _check_tensor(f"exp_avg of parameter {index}", entry["exp_avg"], like)
        squares = _check_tensor(f"exp_avg_sq of parameter {index}", entry["exp_avg_sq"], like)
        if bool((squares < 0).any()):
            raise _Defect(f"exp_avg_sq of parameter {index} has negative values")


_NOT_PLAIN = object()
_SCALARS = (bool, int, float, str, type(None))


def _plain(value: Any) -> Any:
    """``value`` as compared with the trainer's own setting: a tuple as a list (it may come
    back as either), anything but scalars and flat lists of them (a tensor, whose ``==`` is
    not a truth value) as a marker equal to nothing."""
    if type(value) in (tuple, list) and all(type(v) in _SCALARS for v in value):
        return list(value)
    return value if type(value) in _SCALARS else _NOT_PLAIN


def _unpickle(path: Path, data: bytes) -> Any:
    def refuse(reason: str) -> UsageError:
        return UsageError(f"{shown(path)} is not a jetbot-train checkpoint ({reason})")

    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            entries = archive.infolist()
    except Exception:  # zipfile raises many kinds (BadZipFile, NotImplementedError, ...)
        raise refuse("not a zip archive, as torch.save writes") from None
    for entry in entries:
        if entry.compress_type != zipfile.ZIP_STORED or entry.file_size > len(data):
            raise refuse(f"entry {entry.filename[:60]!r} is compressed; torch.save stores "
                         "entries as they are") from None
    try:
        with warnings.catch_warnings():  # torch warns about what a crafted pickle asks for
            warnings.simplefilter("ignore")
            return torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds (pickle, zip, unpickling policy)
        raise refuse(_torch_reason(exc)) from None


def _torch_reason(exc: Exception) -> str:
    """Why ``torch.load`` refused, in a few words: its weights-only refusal is a page that
    suggests loading the file with code execution allowed; only the reason is kept."""
    text = str(exc)
    if text.startswith("Weights only load failed") and "\n" in text:
        body = text.split("\n", 1)[1].split("Check the documentation")[0]
        detail = " ".join(body.split("WeightsUnpickler error:")[-1].split())
        return f"its pickle holds more than tensors and plain data: {detail[:100]}"
    return first_line(exc)[:120]


def load_checkpoint(path: str | Path, *, follow_links: bool = True,
                    label: str | Path | None = None) -> Checkpoint:
    """Read and check a checkpoint (module docstring); ``UsageError`` says what is wrong.
    ``follow_links=False`` refuses a link at ``path`` (a run directory's own checkpoint);
    ``label``: the path messages show (``path`` may be a ``/proc/self/fd`` one)."""
    path = Path(path)
    name = Path(label) if label is not None else path
    try:
        data = safe_file.read_bytes(path, "checkpoint", MAX_CHECKPOINT_BYTES,
                                    follow_links=follow_links)
    except UsageError as exc:
        raise UsageError(str(exc).replace(str(path), shown(name))) from None
    state = _unpickle(name, data)
    if not isinstance(state, dict) or not isinstance(state.get("format"), str) or \
            state["format"] != CHECKPOINT_FORMAT:
        raise UsageError(f"{shown(name)} is not a jetbot-train checkpoint (format "
                         f"{CHECKPOINT_FORMAT})")
    try:
        return _parse(shown(name), state)
    except _Defect as exc:
        raise UsageError(f"checkpoint {shown(name)}: {exc}") from None


def _parse(shown_path: str, state: dict[str, Any]) -> Checkpoint:
    task = state.get("task")
    # A task's name, never loaded here (a checkpoint is no one's command to run code): a run
    # resumes only with the task it names (check_resumable).
    if not isinstance(task, str) or not 0 < len(task) <= MAX_TASK_NAME or \
            not task.isprintable() or not (task in available() or is_code_reference(task)):
        raise _Defect(f"task must be one of {', '.join(available())} or FILE.py:Class, "
                      f"module:Class, got {value_text(task)}")
    algo = state.get("algo", "ppo")
    if not isinstance(algo, str) or algo not in ALGOS:
        raise _Defect(f"algo must be one of {', '.join(ALGOS)}, got {value_text(algo)}")
    if not isinstance(state.get("model_config"), dict):
        raise _Defect(f"model_config must be a dict, got {value_text(state.get('model_config'))}")
    try:
        model_config = ModelConfig.from_dict(state["model_config"])
    except OptionError as exc:
        raise _Defect(f"model_config{exc.name.removeprefix('model')} {exc.problem}") from None
    except UsageError as exc:
        raise _Defect(f"model_config: {exc}") from None
    critic = None
    if state.get("critic") is not None:
        try:
            critic = CriticConfig.from_dict(state["critic"])
        except OptionError as exc:
            raise _Defect(f"{exc.name} {exc.problem}") from None
        total = model_config.parameter_count() + critic.parameter_count(model_config)
        if total > MAX_PARAMETERS:
            raise _Defect(f"the network and its critic have {total:,} parameters, more than "
                          f"{MAX_PARAMETERS:,}")
    weights = state.get("model")
    if not isinstance(weights, dict):
        raise _Defect(f"model must be a dict of weights, got {value_text(weights)}")
    max_speed = _number(state, "max_speed", 0.0, 1.0) if "max_speed" in state else None
    if max_speed == 0.0:
        raise _Defect("max_speed must be a number in (0, 1], got 0.0")
    calibrated = state.get("calibrated", False)
    if not isinstance(calibrated, bool):
        raise _Defect(f"calibrated must be true or false, got {value_text(calibrated)}")
    training = None
    if "optimizer" in state:
        rms = state.get("reward_rms")
        if rms is not None:
            if not isinstance(rms, dict):
                raise _Defect(f"reward_rms must be a dict, got {value_text(rms)}")
            rms = {"mean": _number(rms, "mean", -math.inf),
                   "var": _number(rms, "var", 0.0), "count": _number(rms, "count", 0.0)}
        training = TrainingState(path=shown_path, global_step=_count(state, "global_step"),
                                 update=_count(state, "update"),
                                 wall_s=_number(state, "wall_s", 0.0),
                                 optimizer=state["optimizer"], reward_rms=rms)
    return Checkpoint(path=shown_path, task=task, algo=algo, model_config=model_config,
                      weights=weights, max_speed=max_speed, training=training, critic=critic,
                      calibrated=calibrated)
