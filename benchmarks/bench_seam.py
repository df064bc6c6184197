"""The render-size seam: how far a render at the policy's small size is from a large render
area-averaged down to it (what the real camera's 1280x720 frame becomes after the pipeline's
scaling), over a set of seeded poses around the block; and what rendering at a multiple of
the size and pooling costs and gains.

    python benchmarks/bench_seam.py [--sizes 56 64 84] [--poses 40] [--lens pinhole]
        [--out benchmarks/results]

``--lens pinhole`` (the default here) is the render these figures are about (docs/SIM.md, "The
render size and the seam"); the simulator's own default has been the fisheye since
2026-11-26, whose seam is measured in benchmarks/results/lens_seam/.

Writes seam.json and seam.png (area-averaged reference | direct | 2x pooled, per size) to --out.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import cv2
import numpy as np
from versions import stamp

from jetbot_rt.sim.config import SimConfig
from jetbot_rt.sim.world import JetbotWorld

REFERENCE = (448, 448)
"""The stand-in for the real frame: large enough that area averaging it to the policy's size
is what a 1280x720 frame area-averaged to that size looks like (the pinhole is the same)."""


def poses(n: int, seed: int) -> list[tuple[tuple[float, float, float], tuple[float, float]]]:
    """Robot poses 0.2-1.3 m from a block, the block within +-35 deg of the heading (where
    a policy homing in on it sees it), anywhere in the room."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        bx, by = rng.uniform(-0.8, 0.8, 2)
        distance = rng.uniform(0.2, 1.3)
        bearing = rng.uniform(-math.pi, math.pi)
        x, y = bx - distance * math.cos(bearing), by - distance * math.sin(bearing)
        yaw = bearing + rng.uniform(-0.6, 0.6)
        out.append(((float(x), float(y), float(yaw)), (float(bx), float(by))))
    return out


def area(image: np.ndarray, size: int) -> np.ndarray:
    return cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)


def render_all(size: tuple[int, int], scenes: list,
               lens: str = "pinhole") -> tuple[list[np.ndarray], float]:
    world = JetbotWorld(SimConfig(lens=lens), image_size=size)
    images, seconds = [], 0.0
    for robot_pose, block_xy in scenes:
        world.reset(robot_pose=robot_pose, block_xy=block_xy)
        world.render()  # warm
        t0 = time.perf_counter()
        images.append(world.render())
        seconds += time.perf_counter() - t0
    world.close()
    return images, seconds / len(scenes) * 1e3


def mad(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    pairs = zip(a, b, strict=True)
    return float(np.mean([np.abs(x.astype(np.float32) - y).mean() for x, y in pairs]))


def red_mad(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    """The same over the block's pixels only (red-dominant in the reference)."""
    diffs = []
    for x, y in zip(a, b, strict=True):
        mask = (y[:, :, 0].astype(int) - y[:, :, 1:].max(axis=2)) > 40
        if mask.any():
            diffs.append(np.abs(x.astype(np.float32) - y)[mask].mean())
    return float(np.mean(diffs)) if diffs else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[56, 64, 84])
    parser.add_argument("--poses", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--lens", choices=["pinhole", "fisheye"], default="pinhole")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()

    scenes = poses(args.poses, args.seed)
    reference, reference_ms = render_all(REFERENCE, scenes, args.lens)
    result: dict = {
        "poses": args.poses, "lens": args.lens, "reference": list(REFERENCE),
        "reference_render_ms": reference_ms,
        "loadavg_1min_at_start": round(os.getloadavg()[0], 2), "sizes": {},
    }
    panels = []
    for size in args.sizes:
        ref = [area(r, size) for r in reference]
        direct, direct_ms = render_all((size, size), scenes, args.lens)
        double, double_ms = render_all((2 * size, 2 * size), scenes, args.lens)
        pooled = [area(d, size) for d in double]
        result["sizes"][str(size)] = {
            "direct_render_ms": round(direct_ms, 3),
            "direct_mad": round(mad(direct, ref), 2),
            "direct_block_mad": round(red_mad(direct, ref), 2),
            "2x_pooled_render_ms": round(double_ms, 3),
            "2x_pooled_mad": round(mad(pooled, ref), 2),
            "2x_pooled_block_mad": round(red_mad(pooled, ref), 2),
        }
        shown = zip(ref[:6], direct[:6], pooled[:6], strict=True)
        rows = [np.hstack([r, d, q]) for r, d, q in shown]
        panels.append(cv2.resize(np.vstack(rows), None, fx=448 // size * 0.5 or 1,
                                 fy=448 // size * 0.5 or 1, interpolation=cv2.INTER_NEAREST))
    result["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "seam.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    height = max(p.shape[0] for p in panels)
    strip = np.hstack([np.pad(p, ((0, height - p.shape[0]), (0, 8), (0, 0)),
                              constant_values=255) for p in panels])
    cv2.imwrite(str(args.out / "seam.png"), cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
