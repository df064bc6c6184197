"""The task API (docs/TASKS.md) and the built-in tasks.

A task is a ``Task`` subclass: its scene (``Scene`` of ``Block``, ``Box``, ``Wall``, ``Tape``
pieces) drawn from a seeded generator, its success test and termination, its reward, an
optional privileged expert, its ``max_speed`` and episode length. ``load_task(NAME)`` finds one
by name. Imported by the simulator (scenes) and the trainer (rewards, experts); imports neither
(and no physics engine, no torch).
"""

from __future__ import annotations

from jetbot_rt.tasks.api import Expert, Task, WorldView
from jetbot_rt.tasks.loader import BUILTIN, DEFAULT_TASK, available, load_task
from jetbot_rt.tasks.scene import COLORS, Block, Box, Scene, Tape, Wall

__all__ = ["BUILTIN", "COLORS", "DEFAULT_TASK", "Block", "Box", "Expert", "Scene", "Tape",
           "Task", "Wall", "WorldView", "available", "load_task"]
