"""Hostile checkpoints: a valid tiny one, the ways to spoil it, and a fuzz loop.

``python tests/checkpoint_fuzz.py SEED SECONDS DIR`` mutates the valid checkpoint (its fields
and its bytes) for SECONDS, hands each result to ``jetbot-train export`` (``cli.main`` in this
process) and to the loading a ``--resume`` does, and prints one JSON object per case. Run as a
child process by ``test_train_checkpoint_input.py``, so that a hang ends in its timeout
instead of stalling the suite.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
import torch

from jetbot_rt.errors import UsageError
from jetbot_rt.train.checkpoint import CHECKPOINT_FORMAT, load_checkpoint
from jetbot_rt.train.hyperparams import ModelConfig
from jetbot_rt.train.model import ActorCritic

TINY = ModelConfig(image_size=8, channels=(2, 2, 2), hidden=4, first_kernel=3, first_stride=2)
"""161 parameters: an export takes ~70 ms, so a few seconds try dozens of cases."""
JUNK: tuple[Any, ...] = (
    None, True, -1, 0, 1.5, math.nan, math.inf, 10**30, "x", "\udcff", "a\nb", [], {}, [1, 2],
    (0.9,), {"a": 1}, torch.tensor(1.0), torch.zeros(3), torch.tensor(math.nan),
    torch.zeros(1).expand(10**12),
)
"""Values of every wrong type and range, a view that claims 10^12 elements among them."""


def valid_state() -> dict[str, Any]:
    """What PPO writes (``ppo._save``), for the tiny network, after one Adam step."""
    torch.manual_seed(0)
    model = ActorCritic(TINY)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3, eps=1e-5)
    sum(out.sum() for out in model(torch.rand(2, 8, 8, 3) * 255)).backward()
    optimizer.step()
    return {
        "format": CHECKPOINT_FORMAT, "task": "forward", "model": model.state_dict(),
        "model_config": TINY.to_dict(), "optimizer": optimizer.state_dict(),
        "reward_rms": {"mean": 0.0, "var": 2.0, "count": 10.0}, "global_step": 256,
        "update": 1, "wall_s": 3.5, "max_speed": 0.1, "args": {"seed": 1},
    }


def save(state: Any, path: Path) -> Path:
    torch.save(state, path)
    return path


def _copy(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.clone()
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy(v) for v in value]
    return value


def _spoil_tensor(rng: np.random.Generator, tensor: torch.Tensor) -> Any:
    kind = rng.integers(6)
    if kind == 0:
        return tensor.reshape(-1)[:-1] if tensor.numel() > 1 else tensor.reshape(1, 1)
    if kind == 1:
        return tensor.double()
    if kind == 2:
        spoiled = tensor.clone()
        spoiled.reshape(-1)[rng.integers(max(tensor.numel(), 1))] = float(
            rng.choice([math.nan, math.inf, -math.inf]))
        return spoiled
    if kind == 3:
        return tensor.to_sparse() if tensor.dim() >= 1 else tensor
    if kind == 4:
        return -tensor.abs() - 1  # a negative second moment, a wrong sign elsewhere
    return JUNK[rng.integers(len(JUNK))]


def _spoil_dict(rng: np.random.Generator, table: dict[Any, Any]) -> None:
    keys = list(table)
    kind = rng.integers(4)
    if kind == 0 and keys:
        del table[keys[rng.integers(len(keys))]]
    elif kind == 1:
        table[rng.choice(["extra", "encoder.9.weight", 7, "lr"])] = JUNK[rng.integers(len(JUNK))]
    elif keys:
        key = keys[rng.integers(len(keys))]
        value = table[key]
        if isinstance(value, torch.Tensor):
            table[key] = _spoil_tensor(rng, value)
        elif isinstance(value, dict) and kind == 2:
            _spoil_dict(rng, value)
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            _spoil_dict(rng, value[0])
        else:
            table[key] = JUNK[rng.integers(len(JUNK))]


def mutate_fields(rng: np.random.Generator, state: dict[str, Any]) -> dict[str, Any]:
    """``state`` with one to three fields spoiled, at any depth (weights, model config,
    optimizer state and groups, counters)."""
    state = _copy(state)
    for _ in range(rng.integers(1, 4)):
        where = rng.choice(["top", "model", "model_config", "optimizer", "state", "rms"])
        if where == "top":
            _spoil_dict(rng, state)
        elif where == "state" and isinstance(state.get("optimizer"), dict) and \
                isinstance(state["optimizer"].get("state"), dict) and state["optimizer"]["state"]:
            entries = state["optimizer"]["state"]
            _spoil_dict(rng, entries[list(entries)[rng.integers(len(entries))]])
        elif isinstance(state.get(where if where != "rms" else "reward_rms"), dict):
            _spoil_dict(rng, state[where if where != "rms" else "reward_rms"])
    return state


def mutate_bytes(rng: np.random.Generator, data: bytes) -> bytes:
    """``data`` truncated, with bytes flipped, a range zeroed or garbage inserted."""
    buffer = bytearray(data)
    kind = rng.integers(4)
    if kind == 0:
        return bytes(buffer[: rng.integers(len(buffer))])
    if kind == 1:
        for _ in range(rng.integers(1, 9)):
            buffer[rng.integers(len(buffer))] ^= int(rng.integers(1, 256))
    elif kind == 2:
        start = int(rng.integers(len(buffer)))
        buffer[start:start + int(rng.integers(1, 512))] = bytes(
            len(buffer[start:start + 512]))
    else:
        at = int(rng.integers(len(buffer)))
        buffer[at:at] = rng.bytes(int(rng.integers(1, 64)))
    return bytes(buffer)


def resume_like(path: Path) -> None:
    """What ``--resume`` does with a checkpoint, up to one optimizer step."""
    loaded = load_checkpoint(path)
    resumed = loaded.check_resumable("forward", "ppo")
    model = loaded.model().train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3, eps=1e-5)
    resumed.load_optimizer(optimizer)
    model(torch.rand(1, 8, 8, 3) * 255)[2].sum().backward()
    optimizer.step()


def one_case(path: Path, out: Path) -> dict[str, Any]:
    """``jetbot-train export`` and the resume path on ``path``: exit code, stderr, and any
    exception that escaped (a traceback a user would see)."""
    from jetbot_rt.train.cli import main

    result: dict[str, Any] = {}
    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            result["code"] = main(["export", "--checkpoint", str(path), "--out", str(out)])
    except BaseException:  # what escapes is what this looks for
        result["escaped"] = traceback.format_exc()
    result["stderr"] = stderr.getvalue()
    result["wrote"] = out.exists()
    try:
        resume_like(path)
        result["resume"] = "ok"
    except UsageError as exc:
        result["resume"] = "refused: " + str(exc)
    except BaseException:
        result["resume_escaped"] = traceback.format_exc()
    out.unlink(missing_ok=True)
    return result


def main(seed: int, seconds: float, workdir: Path) -> None:
    rng = np.random.default_rng(seed)
    state = valid_state()
    data = save(state, workdir / "valid.pt").read_bytes()
    deadline = time.monotonic() + seconds
    number = 0
    while time.monotonic() < deadline:
        path = workdir / f"case{number}.pt"
        if number % 2:
            path.write_bytes(mutate_bytes(rng, data))
        else:
            save(mutate_fields(rng, state), path)
        result = one_case(path, workdir / "out.onnx")
        print(json.dumps({"case": number, **result}), flush=True)
        path.unlink()
        number += 1


if __name__ == "__main__":
    main(int(sys.argv[1]), float(sys.argv[2]), Path(sys.argv[3]))
