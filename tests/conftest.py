from __future__ import annotations

import contextlib
import fcntl
import os
import sys
from collections.abc import Iterator
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


@pytest.fixture
def robot(tmp_path) -> Path:
    """A directory with a constant 96x96 policy in it, for ``check_helpers.check``."""
    import policy_models

    policy_models.constant(tmp_path / "policy.onnx", (0.5, 0.5), size=96)
    return tmp_path


# ---- pytest-xdist (README's `pytest -n 2`): tests that must have the machine to themselves --


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "exclusive: under pytest-xdist, runs while no other test runs (it loads "
        "every core on purpose); the other workers wait")


@contextlib.contextmanager
def _flock(path: Path, how: int) -> Iterator[None]:
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    try:
        fcntl.flock(fd, how)
        yield
    finally:
        os.close(fd)  # drops the lock


_held: contextlib.ExitStack | None = None
"""The room, held alone from an exclusive test to the next one on this worker."""


@contextlib.contextmanager
def _room(config: pytest.Config, exclusive: bool, keep: bool) -> Iterator[None]:
    """A readers-writer lock over the workers of one run (flock on files in the run's base
    temp directory, shared by its workers): every test holds the room shared, an
    ``exclusive`` one alone. The turnstile makes a waiting exclusive test go next instead of
    starving while the other worker keeps starting tests. ``keep``: the next test of this
    worker is exclusive too, and gets the room as it is, so that a run of exclusive tests
    (test_record.py's) waits once for the other worker's test, not before each of them."""
    global _held
    if "PYTEST_XDIST_WORKER" not in os.environ:  # one process: nothing runs beside a test
        yield
        return
    stack, _held = _held, None
    if stack is None:
        stack = contextlib.ExitStack()
        shared = config._tmp_path_factory.getbasetemp().parent  # type: ignore[attr-defined]
        turnstile, room = shared / "exclusive.turnstile", shared / "exclusive.room"
        with _flock(turnstile, fcntl.LOCK_EX):
            stack.enter_context(_flock(room, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH))
    try:
        yield
    finally:
        if keep:
            _held = stack
        else:
            stack.close()


def _exclusive(item: pytest.Item | None) -> bool:
    return item is not None and item.get_closest_marker("exclusive") is not None


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    # Around set-up, call and tear-down: module and class fixtures set up for this item too.
    exclusive = _exclusive(item)
    with _room(item.config, exclusive, keep=exclusive and _exclusive(nextitem)):
        yield


WHOLE_FILES = {
    "tests/test_train_cli.py": "its smoke training run (a module fixture) is made once",
    "tests/test_record.py": "its sim recording (a module fixture) is made once",
}
"""Files whose tests one pytest-xdist worker runs, one after another (and first: they are
the longest units). Every other test goes to whichever worker is free. (xdist's own
``--dist loadgroup`` groups nothing on pytest 9.2: pytest-xdist issue #1386.)"""

BOTH_CORES = {
    "tests/test_train_ray.py": "Ray: a GCS, raylets, agents, two actors or trials; the whole "
                               "file, so its one-node class shares one Ray runtime and two Ray "
                               "clusters never start side by side",
    "tests/test_calibrate.py::test_calibrate_in_the_sim_recovers_each_truth_within_tolerance":
        "two sim drives side by side",
    "tests/test_train_cli.py::test_ctrl_c_during_a_dagger_collection_ends_the_workers_at_once":
        "a trainer and its two env workers",
    "tests/test_train_sampler.py::test_training_through_worker_processes_samples_in_them":
        "a trainer and its env workers",
    "tests/test_ppo_asymmetric.py::test_rollouts_carry_the_state_and_bootstrap_from_the_critic"
    "[env-workers]": "a trainer and its env workers",
    "tests/test_children_ignore_cwd.py::test_the_trainers_worker_processes_never_import_from_"
    "the_working_directory": "an evaluation's two workers",
}
"""Tests that keep both cores busy for seconds: one unit, so that they run one after another
on one worker, beside the other worker's lighter tests (mostly a runtime waiting on its
30 Hz), instead of two of them sharing the two cores. Side by side with test_train_cli.py's
trainings and test_calibrate.py's drives, test_train_ray.py took 62-117 s; alone, 41 s."""


def _unit(nodeid: str) -> str:
    """The work unit of a test: ``BOTH_CORES``', its file's for ``WHOLE_FILES``, or its own."""
    path = nodeid.split("::", 1)[0]
    if any(nodeid == key or path == key for key in BOTH_CORES):
        return "both-cores"
    return path if path in WHOLE_FILES else nodeid


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    if config.getvalue("dist") != "load":  # an explicit --dist other than -n's default
        return None
    from xdist.scheduler import LoadScopeScheduling

    class Scheduling(LoadScopeScheduling):
        """A work unit per test, or per ``_unit``; units with the most tests go first
        (``--loadscope-reorder``, xdist's default)."""

        def _split_scope(self, nodeid: str) -> str:
            return _unit(nodeid)

    return Scheduling(config, log)
