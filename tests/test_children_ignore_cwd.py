"""Child processes of ours never import (or run) anything from the working directory.

``python -m`` puts the working directory first on ``sys.path``: a ``jetbot_rt/`` package (or a
``json.py``) planted in a shared directory would run as the operator, root for the service,
whenever someone records from there. Each child the runtime starts is started here from a
directory holding such plants, each of which would leave a marker file if it ever ran:

- the recorder's writer process (``run --record``; ``jetbot-train eval --video`` builds the same
  ``Recorder``), in-process and end to end;
- the trainer's spawned worker processes (``jetbot-train eval`` and ``train``'s env workers);
- ``gst-launch-1.0`` (not Python: it is found on PATH, so the end-to-end run also puts an empty
  entry, which means the working directory, first on PATH).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from runner import RuntimeProcess

from jetbot_rt.recording.reader import Recording
from jetbot_rt.recording.recorder import Recorder, writer_command
from jetbot_rt.runtime.loop import TickResult
from jetbot_rt.runtime.policy import bundled_policy_path

PLANTED_MODULES = ("jetbot_rt/__init__.py", "jetbot_rt/recording/writer_process.py", "json.py",
                   "mmap.py", "signal.py", "errno.py", "pathlib.py", "typing.py", "cv2.py",
                   "numpy/__init__.py")
"""What the writer imports (and the package itself): each would shadow the real one if the
working directory were on ``sys.path``."""


def plant(directory: Path, markers: Path) -> None:
    """Packages, modules and a ``gst-launch-1.0`` that each write a marker when they run."""
    markers.mkdir(exist_ok=True)
    for name in PLANTED_MODULES:
        path = directory / name
        path.parent.mkdir(parents=True, exist_ok=True)
        marker = markers / name.replace("/", "_")
        path.write_text(f"open({str(marker)!r}, 'w').write('ran')\n"
                        "raise SystemExit('planted module ran')\n")
    gst = directory / "gst-launch-1.0"
    gst.write_text(f"#!/bin/sh\necho ran > {markers / 'gst-launch-1.0'}\nexit 1\n")
    gst.chmod(0o755)


def tick(number: int) -> TickResult:
    return TickResult(tick=number, t_start=number / 30, deadline=number / 30,
                      image=np.full((32, 32, 3), number, np.uint8), frame_index=number,
                      frame_age_ms=1.0, mu=[0.5, -0.5], cmd=(0.05, -0.05), infer_ms=1.0,
                      tick_ms=2.0, write_ms=0.1, advance_ms=None, overruns=0, extra={})


def test_the_writer_command_drops_the_working_directory_before_any_import():
    command = writer_command("{}")
    assert command[1] == "-c" and "-m" not in command
    program = command[2]
    assert program.startswith("import sys; sys.path[:] = [p for p in sys.path if p]; ")


def test_the_recorders_writer_never_imports_from_the_working_directory(tmp_path, monkeypatch):
    shared = tmp_path / "shared"
    shared.mkdir()
    plant(shared, tmp_path / "markers")
    monkeypatch.chdir(shared)
    recorder = Recorder("rec", {"source": "test"}, (32, 32), 30.0, t0=0.0)  # relative: cwd
    for number in range(1, 6):
        recorder.observe(tick(number))
    counts = recorder.close({"reason": "test"}, timeout=None)
    assert recorder.process.returncode == 0
    assert counts["frames_written"] == 5 and "error" not in counts
    assert [r["frame"] for r in Recording.open(shared / "rec").ticks] == [0, 1, 2, 3, 4]
    assert sorted(os.listdir(tmp_path / "markers")) == []


@pytest.mark.exclusive  # the writer runs at nice 19 (see test_record.py)
def test_a_recorded_real_run_started_in_a_planted_directory_runs_nothing_from_it(tmp_path):
    runtime = RuntimeProcess(
        tmp_path, "real", bundled_policy_path(), duration=1.0,
        config="[loop]\nwatchdog_timeout = 2.0\nmax_frame_age = 0.5\n"
        '[camera]\nsource = "gst:videotestsrc is-live=true"\nstart_timeout = 5\n')
    plant(tmp_path, tmp_path / "markers")  # the run's working directory is tmp_path
    runtime.args += ["--record", "rec"]
    runtime.env["PATH"] = os.pathsep + runtime.env.get("PATH", os.defpath)
    result = runtime.start().finish(timeout=60)
    assert result.returncode == 0, result.stderr
    assert runtime.board_off()
    assert len(Recording.open(tmp_path / "rec").ticks) == len(result.ticks) > 5
    assert sorted(os.listdir(tmp_path / "markers")) == []



def test_the_trainers_worker_processes_never_import_from_the_working_directory(tmp_path):
    """``jetbot-train eval`` with two workers: its spawned ``python -c`` workers import
    ``multiprocessing``, ``threading`` and the package before anything of ours runs."""
    shared = tmp_path / "shared"
    shared.mkdir()
    markers = tmp_path / "markers"
    plant(shared, markers)
    for name in ("threading.py", "multiprocessing/__init__.py"):
        (shared / name).parent.mkdir(parents=True, exist_ok=True)
        (shared / name).write_text(f"open({str(markers / name.replace('/', '_'))!r}, 'w')\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONSAFEPATH"}
    result = subprocess.run(
        [str(Path(sys.executable).with_name("jetbot-train")), "eval", "--task", "forward",
         "--episodes", "2", "--num-envs", "2", "--no-progress", "--json"],
        cwd=shared, env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["episodes"] == 2
    assert sorted(os.listdir(markers)) == []


def test_the_safe_path_switch_is_set_only_while_the_trainers_workers_start(monkeypatch):
    """A script this process runs afterwards by name (``python tests/x.py``) needs its own
    directory on ``sys.path``: ``PYTHONSAFEPATH`` must not stay in the environment."""
    from jetbot_rt.train.evaluate import evaluate

    monkeypatch.delenv("PYTHONSAFEPATH", raising=False)
    result = evaluate(task="forward", episodes=2, num_workers=2, progress=False)
    assert result["episodes"] == 2
    assert "PYTHONSAFEPATH" not in os.environ
