"""Gymnasium registration of the JetBot tasks.

``gymnasium.make("jetbot_rt:Jetbot-v0", task="NAME")`` makes the env of any task by name
(``jetbot_rt.tasks.load_task``: a built-in, ``FILE.py:Class``, ``module:Class``, an installed
plugin's); the built-ins also have ids of their own (``jetbot_rt:JetbotForward-v0``,
``jetbot_rt:JetbotSeek-v0``). ``make`` imports ``jetbot_rt`` first; its ``__init__`` calls
``register_envs`` when gymnasium is already loaded (it is, inside ``make``), or else once
gymnasium is imported (``jetbot_rt._after_import``): an import of ``jetbot_rt`` made before
gymnasium's runs nothing again. Gymnasium 1.x no longer reads plugin entry points, so these
imports are the hook.
"""

from __future__ import annotations

GENERIC_ID = "Jetbot-v0"
ENV_IDS = {"JetbotForward-v0": "forward", "JetbotSeek-v0": "seek"}


def register_envs() -> None:
    """Register every task id; idempotent (a second call changes nothing)."""
    import gymnasium

    ids = {GENERIC_ID: {}, **{env_id: {"task": task} for env_id, task in ENV_IDS.items()}}
    for env_id, kwargs in ids.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point="jetbot_rt.train.env:JetbotEnv",
                kwargs=kwargs,
                disable_env_checker=False,
            )
