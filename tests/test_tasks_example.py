"""docs/TASKS.md's tutorial task, end to end as a user runs it: examples/tasks/my_task.py
copied to a directory of its own, trained for two updates through ``--task FILE:Class``,
evaluated, and driven by ``jetbot-rt run --backend sim`` with ``[sim] task`` naming it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from runner import run_cli
from train_runner import train_cli

pytest.importorskip("pybullet")

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "tasks" / "my_task.py"


def test_the_tutorial_task_trains_evaluates_and_drives_from_its_own_file(tmp_path):
    task_file = tmp_path / "mine" / "my_task.py"
    task_file.parent.mkdir()
    shutil.copy(EXAMPLE, task_file)
    task = f"{task_file}:ParkAtBlueWall"
    out = tmp_path / "run"
    trained = train_cli("train", "--task", task, "--algo", "ppo", "--timesteps", "128",
                        "--num-envs", "1", "--workers", "0", "--num-steps", "64",
                        "--update-epochs", "1", "--num-minibatches", "2", "--no-progress",
                        "--out", str(out))
    assert trained.returncode == 0, trained.stderr
    policy = out / "policy.onnx"
    assert len((out / "metrics.csv").read_text().splitlines()) == 3  # header, 2 updates

    evaluated = train_cli("eval", "--task", task, "--policy", str(policy), "--episodes", "1",
                          "--num-envs", "1", "--json", "--no-progress")
    assert evaluated.returncode == 0, evaluated.stderr
    result = json.loads(evaluated.stdout)
    assert result["task"] == task and result["episodes"] == 1
    assert result["max_speed"] == 0.3 and result["episode_steps"] == 300

    config = tmp_path / "park.toml"
    config.write_text(f'[sim]\ntask = "{task}"\n')
    driven = run_cli(["run", "--backend", "sim", "--policy", str(policy), "--config",
                      str(config), "--duration", "0.5"])
    assert driven.returncode == 0, driven.stderr
    assert "travelled" in driven.stdout + driven.stderr

    # The same policy without [sim] task: its metadata names a file, which is not run.
    refused = run_cli(["run", "--backend", "sim", "--policy", str(policy), "--duration", "1"])
    assert refused.returncode == 2
    assert "name it yourself: [sim] task" in refused.stderr
