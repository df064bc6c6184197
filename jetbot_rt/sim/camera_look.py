"""The camera's own look: exposure, white balance, gain noise, vignetting and motion blur.

Applied to each rendered frame before the sensor effects of ``camera_model.SensorEffects``
(blur, contrast, brightness, noise), in the order light meets them in a camera: motion blur
(the scene moves while the shutter is open), vignetting (the lens), exposure and white balance
(the sensor's gain per channel, on linear light), gain noise (shot noise of the light times
the gain), then the gamma curve back to 8 bits. All off at the defaults (``[sim] exposure
= 1``, ``white_balance = [1, 1, 1]``, ``gain_noise = vignetting = motion_blur = 0``), and then
the frame passes through untouched.

Motion blur needs the robot's motion: ``apply(image, yaw_rate, speed)``. A turn smears the
image sideways by ``|yaw_rate| * motion_blur * fx`` pixels; driving ahead smears the floor
downwards by ``speed * motion_blur * fy * sin^2(a) / h`` pixels, the angular rate of a floor
point seen ``a`` below the horizon from height ``h``, taken at the lower half's middle
(``a`` = pitch + vfov / 4) for the whole frame: an approximation, the real blur grows towards
the bottom and vanishes at the horizon.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

from jetbot_rt.sim.camera_model import CAMERA_ASPECT

if TYPE_CHECKING:
    from jetbot_rt.sim.config import SimConfig

GAMMA = 2.2
_TO_LINEAR = ((np.arange(256, dtype=np.float32) / 255.0) ** GAMMA).astype(np.float32)
NOISE_STREAM = 26
"""The gain noise's generator is seeded with ``[sim] seed`` and this, apart from
``image_noise``'s, so turning one on leaves the other's draws as they were."""


def line_kernel(length: float) -> np.ndarray | None:
    """A centred 1-D box ``length`` pixels long, sampled: each tap weighs its pixel's overlap
    with the box (an odd number of taps, so the image does not shift), summing to 1. None
    below half a pixel."""
    if length < 0.5:
        return None
    n = math.ceil(length) | 1
    centres = np.arange(n, dtype=np.float64) - (n - 1) / 2
    overlap = np.clip(np.minimum(centres + 0.5, length / 2)
                      - np.maximum(centres - 0.5, -length / 2), 0.0, None)
    return (overlap / overlap.sum()).astype(np.float32)


class CameraLook:
    """``[sim]``'s exposure, white balance, gain noise, vignetting and motion blur for
    frames of one size (the world's render size)."""

    def __init__(self, sim: SimConfig, size: tuple[int, int]) -> None:
        self._exposure = float(sim.exposure)
        self._balance = np.asarray(sim.white_balance, np.float32)
        self._gain_noise = float(sim.gain_noise)
        self._vignetting = float(sim.vignetting)
        self._shutter = float(sim.motion_blur)
        width, height = size
        tan_v = math.tan(math.radians(sim.camera_vfov_deg) / 2)
        self._fy = (height / 2) / tan_v
        self._fx = (width / 2) / (CAMERA_ASPECT * tan_v)
        below = math.radians(sim.camera_pitch_deg + sim.camera_vfov_deg / 4)
        self._floor_rate = math.sin(below) ** 2 / sim.camera_height  # rad/s per m/s
        self._rng = np.random.default_rng([sim.seed, NOISE_STREAM])
        self._gains: np.ndarray | None = None
        self.ideal = (self._exposure == 1.0 and bool(np.all(self._balance == 1.0))
                      and self._gain_noise == 0 and self._vignetting == 0 and self._shutter == 0)
        """Whether frames pass unchanged (decided once: ``apply`` runs every frame)."""
        if not self.ideal:
            y, x = np.mgrid[0:height, 0:width].astype(np.float32)
            r2 = ((x + 0.5 - width / 2) / (width / 2)) ** 2 + ((y + 0.5 - height / 2)
                                                              / (height / 2)) ** 2
            vignette = 1.0 - self._vignetting * np.clip(r2 / 2.0, 0.0, 1.0)  # corner: 1 - v
            self._gains = (vignette[:, :, None] * self._exposure
                           * self._balance[None, None, :]).astype(np.float32)

    def blur_lengths(self, yaw_rate: float, speed: float) -> tuple[float, float]:
        """(sideways, downwards) smear in pixels for this motion during the shutter."""
        return (abs(yaw_rate) * self._shutter * self._fx,
                abs(speed) * self._shutter * self._floor_rate * self._fy)

    def apply(self, image: np.ndarray, yaw_rate: float = 0.0, speed: float = 0.0
              ) -> np.ndarray:
        """The frame as this camera delivers it (uint8 RGB in, uint8 RGB out)."""
        if self.ideal:
            return image
        if self._shutter > 0:
            sideways, down = self.blur_lengths(yaw_rate, speed)
            kx, ky = line_kernel(sideways), line_kernel(down)
            if kx is not None or ky is not None:
                one = np.ones(1, np.float32)
                image = cv2.sepFilter2D(image, -1, kx if kx is not None else one,
                                        ky if ky is not None else one,
                                        borderType=cv2.BORDER_REFLECT)
        assert self._gains is not None
        linear = _TO_LINEAR[image] * self._gains
        if self._gain_noise > 0:
            shot = np.sqrt(np.clip(linear, 0.0, None) + np.float32(0.02))
            noise = self._rng.standard_normal(linear.shape, dtype=np.float32)
            linear += noise * shot * np.float32(self._gain_noise * math.sqrt(self._exposure))
        out = np.clip(linear, 0.0, 1.0) ** np.float32(1 / GAMMA)
        return (out * np.float32(255.0) + np.float32(0.5)).astype(np.uint8)
