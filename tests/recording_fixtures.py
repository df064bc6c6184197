"""A small, valid recording written by the real ``Recorder`` (and its writer process), and
the ways to spoil it, for the tests of the recording reader, replay and report."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
from runner import JETBOT_RT

from jetbot_rt.recording.recorder import Recorder, sha256_of
from jetbot_rt.runtime.loop import TickResult
from jetbot_rt.runtime.policy import OnnxPolicy, bundled_policy_path

TICKS = 20
RATE_HZ = 30.0


def make_recording(path: Path, ticks: int = TICKS) -> Path:
    """``ticks`` ticks of the bundled policy's input size, a safe stop, the end: what a run
    writes, through the real recorder."""
    policy = bundled_policy_path()
    spec = OnnxPolicy.load(policy).spec
    meta = {"source": "test", "backend": "sim", "max_speed": 0.1,
            "policy": {"path": str(policy), "sha256": sha256_of(policy), "metadata": {}},
            "config": {"policy": {"threads": 1, "path": None}}}
    recorder = Recorder(path, meta, (spec.width, spec.height), RATE_HZ, t0=0.0,
                        clock=lambda: ticks / RATE_HZ)
    rng = np.random.default_rng(0)
    for tick in range(1, ticks + 1):
        image = rng.integers(0, 256, (spec.height, spec.width, 3), dtype=np.uint8)
        recorder.observe(TickResult(
            tick=tick, t_start=tick / RATE_HZ, deadline=tick / RATE_HZ, image=image,
            frame_index=tick, frame_age_ms=1.5, mu=[0.25, -0.5], cmd=(0.025, -0.05),
            infer_ms=1.0, tick_ms=2.0, write_ms=0.1, advance_ms=None, overruns=0, extra={}))
    recorder.event("safe_stop", reason="test stop", fault=True, cmd=[0.0, 0.0])
    recorder.close({"reason": "test stop", "exit_code": 3}, timeout=None)
    return path


def read_lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (path / "ticks.jsonl").read_text().splitlines()]


def write_lines(path: Path, records: list[Any]) -> None:
    (path / "ticks.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def jetbot_rt(*args: str, timeout: float = 60.0,
              **kwargs: Any) -> subprocess.CompletedProcess[str]:
    return subprocess.run([JETBOT_RT, *args], capture_output=True, text=True, timeout=timeout,
                          **kwargs)


def assert_refused(proc: subprocess.CompletedProcess[str], *fragments: str) -> None:
    """The promise for bad input: exit 2, one line on stderr naming the problem, no
    traceback."""
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    for fragment in fragments:
        assert fragment in proc.stderr, proc.stderr
