import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(autouse=True)
def private_runtime_dir(tmp_path_factory, monkeypatch):
    """Each test's runtimes get their own control-socket directory, so tests (and a jetbot-rt
    running on the machine) never see each other's sockets."""
    path = tmp_path_factory.mktemp("runtime")
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(path))
    return path
