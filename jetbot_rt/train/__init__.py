"""Training: the Gymnasium env on the PyBullet sim, PPO, ONNX export, evaluation, and the
``jetbot-train`` command. Importing this package registers the Gymnasium ids (and imports
gymnasium, not torch) when gymnasium is installed; without it ``jetbot-train`` names the
missing ``train`` extra in one line instead of a traceback."""

import contextlib
import os

# Torch's OpenMP threads wait for work by sleeping, not spinning (libgomp reads this when torch
# loads it, so it must be set before the first ``import torch``; a value the user set wins).
# Spinning threads that the OS has descheduled -- any time the cores have other work, e.g.
# two update threads on two cores shared with other jobs -- made PPO's update 6x slower
# (benchmarks/bench_train.py, docs/TRAINING.md "Speed").
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

with contextlib.suppress(ImportError):
    from jetbot_rt.train.registration import register_envs

    register_envs()


def __getattr__(name: str) -> object:
    """``from jetbot_rt.train import export_policy`` loads torch then, not with the package."""
    if name == "export_policy":
        from jetbot_rt.train.export import export_policy

        return export_policy
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
