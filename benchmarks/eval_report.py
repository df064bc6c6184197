"""An evaluation's ``--json`` output as the analysis scripts read it (``replay_misses.py``,
``success_by_draw.py``): through the project's safe reader, a device script's ``{"heldout":
..., "blank": ...}`` taken at its held-out part."""

from __future__ import annotations

import argparse
from typing import Any

from jetbot_rt.config.safe_file import read_json


def evaluation_arguments(parser: argparse.ArgumentParser, eval_help: str) -> None:
    """The options every script that reads an evaluation takes: ``--eval`` (the file),
    ``--episodes`` (its first N) and ``--config`` (the config it was run with)."""
    parser.add_argument("--eval", required=True, help=eval_help)
    parser.add_argument("--episodes", type=int, default=None,
                        help="the evaluation's count (default: its own)")
    parser.add_argument("--config", default=None)


def read_evaluation(path: str, episodes: int | None = None
                    ) -> tuple[dict[str, Any], range, set[int]]:
    """The report, its episodes' seeds (the first ``episodes``, default all of its own) and
    the seeds that succeeded."""
    report: Any = read_json(path, "evaluation", 1 << 20)
    report = report.get("heldout", report)
    first = report["seed"]
    return report, range(first, first + (episodes or report["episodes"])), set(report["successes"])
