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
    # The suite's wall time is mostly waiting (real-time runs, subprocesses): a worker that
    # finishes its share takes tests from the other's queue instead of idling while the slow
    # ones left there run. Set here, not in addopts: the robot side's pytest has no xdist.
    if getattr(config.option, "dist", None) == "load":
        config.option.dist = "worksteal"


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


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Within each file, its exclusive tests first (in their order), the others after them (in
    theirs): a file's exclusive tests are one block, the room held from one to the next."""
    files: dict[object, int] = {}
    for item in items:
        files.setdefault(item.path, len(files))
    items.sort(key=lambda item: (files[item.path], not _exclusive(item)))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    # Around set-up, call and tear-down: module and class fixtures set up for this item too.
    exclusive = _exclusive(item)
    with _room(item.config, exclusive, keep=exclusive and _exclusive(nextitem)):
        yield


EXCLUSIVE = {
    "tests/test_record.py": "its recorder's writer runs at nice 19 (see the file); the whole "
                            "file, so its sim recording (a module fixture) is made once",
    "tests/test_fault_load.py::test_two_busy_cores_the_loop_keeps_its_schedule_or_stops_safely":
        "its load is its own",
    "tests/test_first_commands.py::test_gui_under_a_software_rendered_display_keeps_driving":
        "Mesa renders on every core",
    "tests/test_children_ignore_cwd.py::test_a_recorded_real_run_started_in_a_planted_directory_"
    "runs_nothing_from_it": "its recorder's writer runs at nice 19",
}
"""The tests marked ``exclusive``, as one unit that goes first: one worker runs them back to
back (holding the room from one to the next) while the other, after its first test, waits;
then test_record.py's other tests, beside the other worker.
Spread through the run, each of them first waited for the other worker's current test (the
smoke training, a calibration drive: up to 20 s), and so stood idle twice. A test marked
exclusive but not listed here is still run alone, as a unit of its own; the markers decide
who runs alone, this list only when."""

HEAVY = {
    "tests/test_train_ray.py": "Ray: a GCS, raylets, agents, two actors or trials; the whole "
                               "file, so its one-node class shares one Ray runtime and two Ray "
                               "clusters never start side by side",
    "tests/test_train_cli.py": "trainings in this process and in the console script; the whole "
                               "file, so its smoke training run (a module fixture) is made once",
    "tests/test_calibrate.py::test_calibrate_in_the_sim_recovers_each_truth_within_tolerance":
        "two sim drives side by side",
    "tests/test_train_sampler.py::test_training_through_worker_processes_samples_in_them":
        "a trainer and its env workers",
    "tests/test_ppo_asymmetric.py::test_rollouts_carry_the_state_and_bootstrap_from_the_critic"
    "[env-workers]": "a trainer and its env workers",
    "tests/test_children_ignore_cwd.py::test_the_trainers_worker_processes_never_import_from_"
    "the_working_directory": "an evaluation's two workers",
}
"""Tests that keep a core or both busy for many seconds, as one unit (right after the first
ordinary test, so that the other worker takes it): they run one after another on one worker,
beside the other worker's lighter tests (mostly a runtime waiting on its 30 Hz), instead of two
of them sharing the two cores. Side by side with test_train_cli.py's trainings and
test_calibrate.py's drives, test_train_ray.py took 62-117 s; alone, 41 s."""


def _unit(nodeid: str) -> str:
    """The work unit of a test: "exclusive", "heavy" or its own (xdist's own ``--dist
    loadgroup`` groups nothing on pytest 9.2: pytest-xdist issue #1386)."""
    path = nodeid.split("::", 1)[0]
    for name, table in (("exclusive", EXCLUSIVE), ("heavy", HEAVY)):
        if nodeid in table or path in table:
            return name
    return nodeid


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    if config.getvalue("dist") != "load":  # an explicit --dist other than -n's default
        return None
    from collections import OrderedDict

    from xdist.scheduler import LoadScopeScheduling

    class Scheduling(LoadScopeScheduling):
        """Work units by ``_unit``, handed out in this order: "exclusive", the first ordinary
        test, "heavy", then the other tests in collection order, each to whichever worker is
        nearly out of work."""

        ordered = False

        def _split_scope(self, nodeid: str) -> str:
            return _unit(nodeid)

        def _assign_work_unit(self, node: object) -> None:
            if not self.ordered:  # the first assignment: the queue is complete
                self.ordered = True
                units = list(self.workqueue.items())
                first = [(name, dict(sorted(tests.items(), key=lambda t: t[0] not in EXCLUSIVE)))
                         for name, tests in units if name == "exclusive"]  # whole files last
                heavy = [u for u in units if u[0] == "heavy"]
                rest = [u for u in units if u[0] not in ("exclusive", "heavy")]
                self.workqueue = OrderedDict(first + rest[:1] + heavy + rest[1:])
            super()._assign_work_unit(node)  # type: ignore[arg-type]

    return Scheduling(config, log)
