"""Gather a run of ``proof.sh`` into one results file: each recording's length and human
ticks, each fine-tune's ``finetune.json``, each evaluation's success, with the machine and
the versions.

    python benchmarks/drive/collect.py WORK_DIR [--out benchmarks/results/drive_finetune.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from versions import cpu_model, stamp

from jetbot_rt.config.safe_file import read_json
from jetbot_rt.errors import UsageError
from jetbot_rt.recording.reader import Recording

JSON_LIMIT = 1 << 20
"""bytes; a summary or an evaluation is a few kB."""


def recording(path: Path) -> dict:
    """A recording's length, human ticks, episodes and takeovers, read as ``finetune`` reads
    it (the recording reader: regular files, size caps, every record checked)."""
    found = Recording.open(path)
    ticks = found.ticks
    run = found.summary.get("run", {})
    return {"ticks": len(ticks), "minutes": round(len(ticks) / 30 / 60, 2),
            "human_ticks": sum(t.get("driver") == "human" and t.get("human") is not None
                               for t in ticks),
            "episodes": sum(e["event"] == "episode_end" for e in found.events),
            "takeovers": sum(e["event"] == "takeover" for e in found.events),
            "achieved_hz": run.get("achieved_hz"), "overruns": run.get("overruns"),
            "motors_confirmed_zero": run.get("motors_confirmed_zero")}


def evaluation(path: Path) -> dict | None:
    """The evaluation's figures; None for one still being written."""
    try:
        report = read_json(path, "evaluation", JSON_LIMIT)
    except UsageError as exc:
        print(f"{exc}: left out", file=sys.stderr)
        return None
    return {key: report.get(key) for key in ("success_rate", "mean_final_distance", "ablate",
                                             "wall_s", "seed")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--out", type=Path,
                        default=Path(__file__).parents[1] / "results" / "drive_finetune.json")
    args = parser.parse_args()
    work = args.work
    result = {
        "what": "jetbot-rt drive / jetbot-train finetune proof in the simulator (issue 27, "
                "docs/DRIVE.md)",
        "date": time.strftime("%Y-%m-%d"),
        "machine": {"cpu": cpu_model(), "cores": os.cpu_count(),
                    "python": platform.python_version(),
                    "loadavg_1min_at_collect": round(os.getloadavg()[0], 2)},
        "hidden_world": "benchmarks/drive/hidden_world.toml",
        "procedure": f"bash benchmarks/drive/proof.sh {work}, then python "
                     f"benchmarks/drive/collect.py {work}",
        "names": "ft_X_dK: a fine-tune (its recordings, label_delay K, sim_share in "
                 "finetunes); evaluations: <policy>_<world>; hidden: "
                 "hidden_world.toml, randomized: the task's randomization, _blank: "
                 "--ablate blank; bundled_seek: the seek.onnx bundled at the run's commit",
        "recordings": {p.name: recording(p) for p in sorted(work.iterdir())
                       if (p / "summary.json").is_file()},
        "finetunes": {p.name: read_json(p / "finetune.json", "fine-tune summary", JSON_LIMIT)
                      for p in sorted(work.glob("ft_*")) if (p / "finetune.json").is_file()},
        "evaluations": {},
    }
    for path in sorted(work.glob("eval_*.json")):
        found = evaluation(path)
        if found is not None:
            # proof.sh names the bundled policy by its directory, "policies"
            name = path.stem[len("eval_"):].replace("policies_", "bundled_seek_", 1)
            result["evaluations"][name] = found
    args.out.write_text(json.dumps(stamp(result), indent=1) + "\n")
    print(f"wrote {args.out}: {len(result['recordings'])} recordings, "
          f"{len(result['finetunes'])} fine-tunes, {len(result['evaluations'])} evaluations")


if __name__ == "__main__":
    main()
