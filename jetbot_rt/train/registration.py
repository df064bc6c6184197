"""Gymnasium registration of the JetBot tasks.

``gymnasium.make("jetbot_rt:JetbotForward-v0")`` imports ``jetbot_rt`` first; its
``__init__`` calls ``register_envs`` when gymnasium is already loaded (it is, inside
``make``). Gymnasium 1.x no longer reads plugin entry points, so that import is the hook.
"""

from __future__ import annotations

ENV_IDS = {"JetbotForward-v0": "forward", "JetbotSeek-v0": "seek"}


def register_envs() -> None:
    """Register every task id; idempotent (a second call changes nothing)."""
    import gymnasium

    for env_id, task in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point="jetbot_rt.train.env:JetbotEnv",
                kwargs={"task": task},
                disable_env_checker=False,
            )
