"""``run_record()``: a results file's command and date. ``stamp(result)``: a benchmark's
results with the versions it ran with (python, numpy, torch, onnxruntime, opencv, pybullet,
gymnasium, jetbot_rt, the git commit), for each script to call where it writes its JSON:
``json.dumps(stamp(result))``; ``write_results`` writes the stamped JSON and its Markdown
table side by side. The same record as ``jetbot-train eval --json``'s ``versions``
(jetbot_rt/train/versions.py)."""

from __future__ import annotations

import datetime
import json
import platform
import shlex
import sys
from pathlib import Path
from typing import Any

from jetbot_rt.train.versions import versions


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (``platform.processor()`` where it has
    none), for a results file's ``machine``."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def run_record() -> dict[str, str]:
    """The ``command`` that ran this benchmark (as typed from the repository's root) and the
    ``date`` it started, UTC to the minute: the first keys of every results file."""
    script = f"benchmarks/{Path(sys.argv[0]).name}"
    return {"command": shlex.join(["python", script, *sys.argv[1:]]),
            "date": f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC"}


def stamp(result: Any) -> Any:
    """``result`` (a dict) with ``versions`` added; a list of rows becomes
    ``{"rows": result, "versions": ...}``."""
    if isinstance(result, dict):
        return {**result, "versions": versions()}
    return {"rows": result, "versions": versions()}


def write_results(out: Path, name: str, result: dict[str, Any], markdown: str) -> None:
    """``out/NAME.json`` (``result`` stamped) and ``out/NAME.md`` (``markdown``, also
    printed)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    (out / f"{name}.md").write_text(markdown)
    print(markdown)
