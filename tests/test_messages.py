"""What a newcomer reads names the real rule, and a documented figure its versions."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from jetbot_rt.tasks import load_task
from jetbot_rt.train.evaluate import success_rule


def test_the_eval_line_states_each_tasks_whole_success_rule() -> None:
    assert success_rule(load_task("forward")) == "final distance < 0.15 m"
    seek = load_task("seek")
    rule = success_rule(seek)
    assert rule is not None and rule.startswith("final distance < 0.15 m and ")
    assert f"the block pushed less than {seek.max_block_shift:g} m" in rule
    assert success_rule(load_task("avoid")) is None, "not a distance task: no such line"


def test_a_results_file_names_the_versions_it_ran_with() -> None:
    benchmarks = Path(__file__).resolve().parents[1] / "benchmarks"
    script = ("import json, versions; print(json.dumps(versions.stamp({'success_rate': 0.97})))")
    proc = subprocess.run([sys.executable, "-c", script], cwd=benchmarks, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["success_rate"] == 0.97
    stack = result["versions"]
    for name in ("python", "numpy", "torch", "onnxruntime", "opencv", "pybullet", "gymnasium",
                 "jetbot_rt", "git"):
        assert name in stack
    assert stack["onnxruntime"] and stack["opencv"] and stack["numpy"]
