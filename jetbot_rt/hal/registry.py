"""Backends by name. Each backend module registers a factory; heavy modules are imported
only when their backend is asked for, so ``--backend real`` never imports pybullet."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from jetbot_rt.errors import UsageError
from jetbot_rt.hal.base import DEFAULT_FRAME_SIZE
from jetbot_rt.workstation import sim_problem

if TYPE_CHECKING:
    from jetbot_rt.config.sections import Config
    from jetbot_rt.hal.base import Robot

# name -> module that defines ``build_backend(config, options)``
BACKEND_MODULES: dict[str, str] = {
    "sim": "jetbot_rt.sim.backend",
    "real": "jetbot_rt.hal.real",
}


class BackendOptions:
    """Run-time facts a backend may need beyond the config file."""

    def __init__(self, frame_size: tuple[int, int] = DEFAULT_FRAME_SIZE,
                 gui: bool = False, task: str | None = None) -> None:
        self.frame_size = frame_size  # (width, height) the policy wants
        self.gui = gui
        self.task = task  # the task the policy was trained for (its metadata), if it says


def make_backend(name: str, config: Config, options: BackendOptions | None = None) -> Robot:
    """The backend's ``Robot``, not yet connected."""
    if name not in BACKEND_MODULES:
        known = ", ".join(sorted(BACKEND_MODULES))
        raise UsageError(f"unknown backend {name!r} (known: {known})")
    if name == "sim":
        problem = sim_problem()
        if problem:
            raise UsageError(f"--backend sim: {problem}")
    module = importlib.import_module(BACKEND_MODULES[name])
    return module.build_backend(config, options or BackendOptions())
