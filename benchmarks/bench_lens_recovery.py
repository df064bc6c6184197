"""Recovered versus true lens: ``jetbot-rt calibrate --camera --backend sim --config TRUTH``
for each truth, the fitted ``[sim]`` lens keys against the truth's (docs/CALIBRATION.md).

    python benchmarks/bench_lens_recovery.py [--out benchmarks/results]

Writes lens_recovery.json and lens_recovery.md to --out.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

from bench_sim import machine
from versions import write_results

from jetbot_rt.calibration.intrinsics import Lens, radial_error_px
from jetbot_rt.config.sections import load_config

TRUTHS = {
    "datasheet, equidistant": {"lens_focal": 1.0194},
    "wide, barrel": {"lens_focal": 0.95, "lens_k1": 0.05, "lens_k2": -0.02},
    "narrower, pincushion, off-centre": {"lens_focal": 1.1, "lens_center": [0.49, 0.51],
                                         "lens_k1": -0.04, "lens_k2": 0.01},
    "wider still, strong barrel": {"lens_focal": 0.9, "lens_k1": 0.08, "lens_k2": -0.03,
                                   "lens_k3": 0.01},
    "datasheet, mild pincushion": {"lens_focal": 1.0194, "lens_k1": -0.02},
}


def run(name: str, truth: dict, where: Path) -> dict:
    (where / "truth.toml").write_text('[sim]\nlens = "fisheye"\n' + "".join(
        f"{k} = {v!r}\n" for k, v in truth.items()))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "jetbot_rt.cli", "calibrate", "--camera",
                           "--backend", "sim", "--config", "truth.toml", "--record", "views",
                           "--out", "lens.toml"], cwd=where, capture_output=True, text=True,
                          check=True)
    wall = time.perf_counter() - t0
    text = (where / "lens.toml").read_text()
    fitted = Lens.from_sim(load_config(str(where / "lens.toml")).sim)
    want = Lens.from_sim(load_config(str(where / "truth.toml")).sim)
    views = text.split(":", 1)[1].split(" views")[0].strip()
    rms = float(text.split("reprojection rms ")[1].split(" px")[0])
    edge, corner = radial_error_px(want, fitted)
    return {"name": name, "truth": truth, "views": views, "rms_px": rms,
            "focal": round(fitted.focal, 4), "focal_error_pct": round(
                100 * (fitted.focal / want.focal - 1), 2),
            "center": [round(v, 4) for v in fitted.center],
            "k": [round(v, 4) for v in fitted.k],
            "radial_error_px_edge": round(edge, 2), "radial_error_px_corner": round(corner, 2),
            "wall_s": round(wall, 1), "toml": text}


def markdown(result: dict) -> str:
    lines = ["# Recovered versus true lens", "", f"`{result['command']}`, {result['date']}, "
             f"{result['machine']['cpu']}, {result['machine']['cores']} cores.", "",
             "| truth | true focal / centre / k1, k2 | views found of 15 | fitted focal "
             "(error) | fitted centre | fitted k1..k4 | radial error px at 640x360: side "
             "edge / corner | rms px | wall s |", "| --- | --- | --- | --- | --- | --- | --- "
             "| --- | --- |"]
    for r in result["rows"]:
        t = r["truth"]
        lines.append(
            f"| {r['name']} | {t.get('lens_focal')} / {t.get('lens_center', [0.5, 0.5])} / "
            f"{t.get('lens_k1', 0.0)}, {t.get('lens_k2', 0.0)} | {r['views']} | {r['focal']} "
            f"({r['focal_error_pct']:+} %) | {r['center']} | {r['k']} | "
            f"{r['radial_error_px_edge']} / {r['radial_error_px_corner']} | {r['rms_px']} | "
            f"{r['wall_s']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()
    result: dict = {"command": "python " + " ".join([Path(sys.argv[0]).as_posix(),
                                                     *sys.argv[1:]]),
                    "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                    "machine": machine(), "rows": []}
    for name, truth in TRUTHS.items():
        with tempfile.TemporaryDirectory() as where:
            result["rows"].append(run(name, truth, Path(where)))
            print(result["rows"][-1], flush=True)
    write_results(args.out, "lens_recovery", result, markdown(result))


if __name__ == "__main__":
    main()
