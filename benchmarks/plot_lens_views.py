"""The pinhole and the fisheye side by side: the same poses rendered at 320x180 through
``[sim] lens = "pinhole"``, the datasheet fisheye and a wider barrel fisheye, and the
policy's 56x56 through the pinhole and the datasheet fisheye (enlarged).

    python benchmarks/plot_lens_views.py [--out docs/images/lens_views.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from jetbot_rt.sim.config import SimConfig
from jetbot_rt.sim.world import JetbotWorld

LENSES = {
    "pinhole": {},
    "fisheye (datasheet)": {"lens": "fisheye"},
    "fisheye (focal 0.95, k1 0.05)": {"lens": "fisheye", "lens_focal": 0.95, "lens_k1": 0.05,
                                      "lens_k2": -0.02},
}
POSES = [((-0.6, 0.0, 0.0), (0.3, 0.0)), ((-0.2, 0.4, -0.6), (0.4, 0.0)),
         ((0.6, -0.9, 2.2), (0.3, 0.0))]


def render(sim: dict, size: tuple[int, int], pose: tuple, block: tuple) -> np.ndarray:
    with JetbotWorld(SimConfig(**sim), image_size=size) as world:
        world.reset(robot_pose=pose, block_xy=block)
        return world.render()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path,
                        default=Path(__file__).parents[1] / "docs" / "images" / "lens_views.png")
    args = parser.parse_args()
    rows = []
    for pose, block in POSES:
        tiles = [render(sim, (320, 180), pose, block) for sim in LENSES.values()]
        for sim in list(LENSES.values())[:2]:
            small = render(sim, (56, 56), pose, block)
            tiles.append(cv2.resize(small, (180, 180), interpolation=cv2.INTER_NEAREST))
        rows.append(np.hstack([np.pad(t, ((2, 2), (2, 2), (0, 0)), constant_values=255)
                               for t in tiles]))
    header = np.full((24, rows[0].shape[1], 3), 255, np.uint8)
    x = 6
    for name in [*LENSES, "56x56 pinhole", "56x56 fisheye"]:
        cv2.putText(header, name, (x, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1,
                    cv2.LINE_AA)
        x += 324 if not name.startswith("56") else 184
    image = np.vstack([header, *rows])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    print(args.out)


if __name__ == "__main__":
    main()
