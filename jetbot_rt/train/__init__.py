"""Training: the Gymnasium env on the PyBullet sim, PPO, ONNX export, evaluation, and the
``jetbot-train`` command. Importing this package registers the Gymnasium ids (and imports
gymnasium, not torch) when gymnasium is installed; without it ``jetbot-train`` names the
missing ``train`` extra in one line instead of a traceback."""

import contextlib

with contextlib.suppress(ImportError):
    from jetbot_rt.train.registration import register_envs

    register_envs()
