"""The fisheye lens in the simulator: PyBullet renders a pinhole; a fisheye frame is a wider
pinhole render warped through a precomputed map (``cv2.remap``) to the frame's size.

For each pixel of the fisheye frame the map holds where its ray lands in the pinhole render
(``calibration.intrinsics.Lens.rays``: the same model that ``jetbot-rt calibrate --camera``
fits). The pinhole is as wide as the frame's widest rays and sampled as densely as the fisheye
frame at its centre, where the fisheye magnifies most; towards the edges the fisheye squeezes
several render pixels into one (docs/SIM.md, "The lens").
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import TYPE_CHECKING

import cv2
import numpy as np

from jetbot_rt.calibration.intrinsics import Lens

if TYPE_CHECKING:
    from jetbot_rt.sim.config import SimConfig

RENDER_SCALE = 1.0
"""Pinhole render pixels per fisheye pixel at the image centre."""


class FisheyeWarp:
    """The pinhole to render (``vfov_deg``, ``aspect``, ``render_size``) and the map from it
    to a fisheye frame of ``size`` (width, height)."""

    def __init__(self, lens: Lens, size: tuple[int, int]) -> None:
        width, height = size
        self.size = size
        x, y = lens.rays(width, height)
        half_x, half_y = float(np.abs(x).max()), float(np.abs(y).max())
        matrix = lens.matrix(width, height)
        self.render_size = (max(2, math.ceil(2 * half_x * matrix[0, 0] * RENDER_SCALE)),
                            max(2, math.ceil(2 * half_y * matrix[1, 1] * RENDER_SCALE)))
        self.vfov_deg = math.degrees(2 * math.atan(half_y))
        self.aspect = half_x / half_y
        rw, rh = self.render_size
        # render pixel i's centre shows x = (2 (i + 0.5) / rw - 1) * half_x (world.pixel_centred)
        map_x = ((x / half_x + 1) * rw / 2 - 0.5).astype(np.float32)
        map_y = ((y / half_y + 1) * rh / 2 - 0.5).astype(np.float32)
        self._map1, self._map2 = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)

    def warp(self, image: np.ndarray) -> np.ndarray:
        """The fisheye frame from a pinhole render of ``render_size``."""
        return cv2.remap(image, self._map1, self._map2, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)


@lru_cache(maxsize=64)
def _warp(lens: Lens, size: tuple[int, int]) -> FisheyeWarp:
    return FisheyeWarp(lens, size)


def lens_warp(sim: SimConfig, size: tuple[int, int]) -> FisheyeWarp | None:
    """The warp for ``[sim]``'s lens at ``size``, or None for the pinhole. Cached: a
    randomized episode's lens is a new map (about 0.3 ms at 56x56), a repeated one is not."""
    if sim.lens != "fisheye":
        return None
    return _warp(Lens.from_sim(sim), (int(size[0]), int(size[1])))
