"""``--device``: where the PPO learner (network, rollout buffers, optimizer) lives.

``auto`` is CUDA when torch sees a GPU, else the CPU; ``cpu``; ``cuda`` or ``cuda:N``. A CUDA
request on a machine without CUDA is a usage error (one line, exit 2), raised before any env
starts. The envs, Ray actors, checkpoints and the ONNX export stay device-free: frames come in
as numpy and go to the device once, actions leave as CPU numpy, checkpoints hold CPU tensors.
"""

from __future__ import annotations

import re
from typing import Any

import torch

from jetbot_rt.train.hyperparams import OptionError

DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:\d+)?")


def resolve_device(name: str) -> torch.device:
    """The ``torch.device`` called ``name``; ``OptionError`` if it cannot be had here."""
    if not DEVICE_PATTERN.fullmatch(name):
        raise OptionError("device", f"must be auto, cpu, cuda or cuda:N, got {name!r}")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = ("this torch is built without CUDA" if torch.version.cuda is None
                   else "no CUDA GPU is visible")
            raise OptionError("device", f"{name}: CUDA is not available ({why}); use cpu or "
                                        "auto")
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise OptionError("device", f"{name}: this machine has {count} CUDA device(s) "
                                        f"(cuda:0 .. cuda:{count - 1})")
    return device


def to_cpu(state: Any) -> Any:
    """A state dict (nested dicts/lists of tensors, as an optimizer's) with every tensor on
    the CPU, so a checkpoint written on a GPU loads anywhere."""
    if isinstance(state, torch.Tensor):
        return state.detach().cpu()
    if isinstance(state, dict):
        return {key: to_cpu(value) for key, value in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(to_cpu(value) for value in state)
    return state


__all__ = ["resolve_device", "to_cpu"]
