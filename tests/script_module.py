"""A repository script (``benchmarks/``, ``scripts/``) loaded as a module by the tests. The
scripts are no package: each is loaded from its file, with its own directory on the path for
the imports of its neighbours (``from replay_misses import ...``) for the test's duration."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


def load_script(relative: str, monkeypatch: pytest.MonkeyPatch | None = None) -> ModuleType:
    path = ROOT / relative
    if monkeypatch is not None:
        monkeypatch.syspath_prepend(str(path.parent))
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
