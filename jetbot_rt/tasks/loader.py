"""Tasks by name: a built-in, ``path/to/file.py:Class``, ``package.module:Class``, or a name an
installed package registers in the entry point group ``jetbot_rt.tasks`` (the way pytest and
Gymnasium find plugins), e.g. in its ``pyproject.toml``::

    [project.entry-points."jetbot_rt.tasks"]
    park = "my_package.tasks:Park"

Loading a file or module task runs its code: that is what naming it asks for. The working
directory is never searched implicitly: a module is imported with it off ``sys.path``, and a
file is read by its path (through ``config.safe_file``) and run as a module of its own.
"""

from __future__ import annotations

import hashlib
import importlib
import os
import sys
import types
from pathlib import Path
from typing import Any, Callable

from jetbot_rt.errors import UsageError
from jetbot_rt.tasks.api import Task

ENTRY_POINT_GROUP = "jetbot_rt.tasks"
MAX_TASK_FILE = 1024 * 1024
"""Bytes; a task file larger than this is refused."""


def _forward() -> type[Task]:
    from jetbot_rt.tasks.forward import Forward

    return Forward


def _seek() -> type[Task]:
    from jetbot_rt.tasks.seek import Seek

    return Seek


def _follow() -> type[Task]:
    from jetbot_rt.tasks.follow import Follow

    return Follow


def _avoid() -> type[Task]:
    from jetbot_rt.tasks.avoid import Avoid

    return Avoid


BUILTIN: dict[str, Callable[[], type[Task]]] = {"forward": _forward, "seek": _seek,
                                                "follow": _follow, "avoid": _avoid}
"""The tasks that ship with the package, by name."""
DEFAULT_TASK = "forward"


def _entry_points() -> dict[str, Any]:
    from importlib.metadata import entry_points

    found = entry_points()
    group = (found.select(group=ENTRY_POINT_GROUP) if hasattr(found, "select")
             else found.get(ENTRY_POINT_GROUP, ()))  # Python 3.8, 3.9
    return {point.name: point for point in group}


def available() -> list[str]:
    """Names a bare NAME may be: the built-ins, then the installed packages' tasks."""
    return [*BUILTIN, *sorted(set(_entry_points()) - set(BUILTIN))]


def is_code_reference(name: str) -> bool:
    """``FILE.py:Class`` or ``module:Class``: a name that runs code nobody installed for it."""
    return ":" in name


def _unknown(name: str) -> UsageError:
    return UsageError(f"unknown task {name!r} (available: {', '.join(available())}; or "
                      "path/to/file.py:Class, package.module:Class)")


def _module_from_file(path_text: str) -> types.ModuleType:
    from jetbot_rt.config.safe_file import read_text

    path = Path(path_text).expanduser().resolve()
    source = read_text(path, "task file", MAX_TASK_FILE)
    name = "jetbot_rt_user_task_" + hashlib.sha256(str(path).encode()).hexdigest()[:16]
    if name in sys.modules:
        return sys.modules[name]
    module = types.ModuleType(name)
    module.__file__ = str(path)
    sys.modules[name] = module  # dataclasses and pickle look classes up here
    try:
        exec(compile(source, str(path), "exec"), module.__dict__)
    except SyntaxError:
        del sys.modules[name]
        raise
    except Exception as exc:
        del sys.modules[name]
        raise UsageError(f"task file {path}{_where(exc, str(path))}: "
                         f"{type(exc).__name__}: {exc}") from None
    return module


def _where(exc: BaseException, filename: str) -> str:
    """``:LINE`` of the deepest frame of ``exc`` in ``filename``, if any."""
    line = ""
    trace = exc.__traceback__
    while trace is not None:
        if trace.tb_frame.f_code.co_filename == filename:
            line = f":{trace.tb_lineno}"
        trace = trace.tb_next
    return line


def _import_module(name: str) -> types.ModuleType:
    """``importlib.import_module`` with the working directory (and '') off ``sys.path``."""
    cwd = os.getcwd()
    saved = list(sys.path)
    sys.path[:] = [p for p in sys.path if p and os.path.abspath(p) != cwd]
    try:
        return importlib.import_module(name)
    finally:
        kept = [p for p in sys.path if p not in saved]  # what the module added stays
        sys.path[:] = saved + kept


def _task_class(name: str) -> type[Task]:
    if name in BUILTIN:
        return BUILTIN[name]()
    if not is_code_reference(name):
        point = _entry_points().get(name)
        if point is None:
            raise _unknown(name)
        found = point.load()
        where = f"entry point {name!r} ({point.value})"
    else:
        source, _, attribute = name.rpartition(":")
        if not source or not attribute.isidentifier():
            raise _unknown(name)
        try:
            module = (_module_from_file(source) if source.endswith(".py")
                      else _import_module(source))
        except ImportError as exc:
            raise UsageError(f"task {name!r}: cannot import {source!r}: {exc}") from None
        except SyntaxError as exc:
            raise UsageError(f"task {name!r}: {exc.filename}:{exc.lineno}: {exc.msg}") from None
        found = getattr(module, attribute, None)
        if found is None:
            raise UsageError(f"task {name!r}: {source} has no {attribute!r}")
        where = name
    if not (isinstance(found, type) and issubclass(found, Task)):
        raise UsageError(f"task {where}: not a subclass of jetbot_rt.tasks.Task")
    return found


_LOADED: dict[str, Task] = {}


def load_task(name: str | Task) -> Task:
    """The task called ``name`` (an instance; a ``Task`` is returned as is). ``UsageError``,
    one line, for a name that is none (listing what is available) or a class that is no task."""
    if isinstance(name, Task):
        return name
    if not isinstance(name, str) or not name:
        raise _unknown(str(name))
    if name not in _LOADED:
        cls = _task_class(name)
        try:
            task = cls()
        except Exception as exc:  # the user's __init__
            raise UsageError(f"task {name!r}: {cls.__name__}() failed: "
                             f"{type(exc).__name__}: {exc}") from None
        steps, speed = task.episode_steps, task.max_speed
        if not (isinstance(steps, int) and steps >= 1 and isinstance(speed, (int, float))
                and 0 < speed <= 1):
            raise UsageError(f"task {name!r}: episode_steps must be an integer >= 1 and "
                             f"max_speed a number in (0, 1], got {steps!r}, {speed!r}")
        _LOADED[name] = task
    return _LOADED[name]


def describe() -> str:
    """One line per available task, for ``--help``."""
    lines = []
    for name in available():
        try:
            lines.append(f"{name} -- {load_task(name).description}")
        except Exception as exc:  # a broken plugin must not break --help
            lines.append(f"{name} -- (cannot load: {exc})")
    return "; ".join(lines)
