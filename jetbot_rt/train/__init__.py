"""Training: the Gymnasium env on the PyBullet sim, PPO, ONNX export, evaluation, and the
``jetbot-train`` command. Importing this package registers the Gymnasium ids (and imports
gymnasium, not torch)."""

from jetbot_rt.train.registration import register_envs

register_envs()
