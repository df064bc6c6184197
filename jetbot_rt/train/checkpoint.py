"""Trainer checkpoints: one ``torch.save`` dict with a format tag, so a foreign file is refused
with one clear line instead of a traceback from deep inside ``torch.load``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from jetbot_rt.errors import UsageError
from jetbot_rt.train.model import ActorCritic, ModelConfig

CHECKPOINT_FORMAT = "jetbot_rt.ppo/1"
CHECKPOINT_NAME = "checkpoint.pt"


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write atomically: a run killed mid-save leaves the previous checkpoint intact."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": CHECKPOINT_FORMAT, **state}, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise UsageError(f"checkpoint {path} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds (pickle, zip, unpickling policy)
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UsageError(f"{path} is not a jetbot-train checkpoint ({reason[:120]})") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise UsageError(f"{path} is not a jetbot-train checkpoint (format {CHECKPOINT_FORMAT})")
    return state


def model_from_checkpoint(state: dict[str, Any]) -> ActorCritic:
    model = ActorCritic(ModelConfig.from_dict(state["model_config"]))
    model.load_state_dict(state["model"])
    model.eval()
    return model
