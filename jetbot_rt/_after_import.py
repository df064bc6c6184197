"""Run a function once a module has been imported, whenever that happens: the hook that
registers the Gymnasium ids (``jetbot_rt/__init__.py``) when gymnasium is imported after
``jetbot_rt``. Robot side (Python 3.8): it imports nothing beyond the standard library, and a
module that is never imported (gymnasium on the robot) costs one string comparison per import.
"""

from __future__ import annotations

import contextlib
import sys

TYPE_CHECKING = False
if TYPE_CHECKING:  # typing itself is not imported: this module is imported with jetbot_rt
    from typing import Any, Callable


class _Then:
    """A loader: the module's own, then ``then``. (No ``importlib.abc`` base: importing it
    costs more than all of ``jetbot_rt/__init__``; the import system asks for these methods.)"""

    def __init__(self, loader: Any, hook: AfterImport) -> None:
        self.loader = loader
        self.hook = hook

    def create_module(self, spec: Any) -> Any:
        return self.loader.create_module(spec)

    def exec_module(self, module: Any) -> None:
        # The module keeps its own loader (its resources, its source are read through it).
        module.__loader__ = module.__spec__.loader = self.loader
        self.hook.remove()
        self.loader.exec_module(module)
        self.hook.then()


class AfterImport:
    """A finder ahead of the others that answers only for ``name``: it asks the finders after
    it, and loads what they found with ``then`` run once the module is loaded, then leaves
    ``sys.meta_path``. A spec looked up without an import (``importlib.util.find_spec``) keeps
    it in place, for the import that may follow."""

    def __init__(self, name: str, then: Callable[[], None]) -> None:
        self.name = name
        self.then = then

    def install(self) -> None:
        if self not in sys.meta_path:
            sys.meta_path.insert(0, self)

    def remove(self) -> None:
        with contextlib.suppress(ValueError):
            sys.meta_path.remove(self)

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> Any | None:
        if fullname != self.name:
            return None
        for finder in list(sys.meta_path):
            find = getattr(finder, "find_spec", None)
            if finder is self or find is None:
                continue
            spec = find(fullname, path, target)
            if spec is not None:
                if spec.loader is not None and hasattr(spec.loader, "exec_module"):
                    spec.loader = _Then(spec.loader, self)
                return spec
        return None
