"""The simulated camera as built: its mount, its latency and what its sensor does to a frame.

- Mount: the optical centre 0.06 m ahead of the axle midpoint at ``[sim] camera_height``
  above the floor, tilted ``camera_pitch_deg`` down, a pinhole of ``camera_vfov_deg``
  vertical field of view (docs/SIM.md, "The camera").
- Latency: a frame delivered at sub-step ``n`` shows the world at sub-step
  ``n - round(camera_latency * physics_hz)``. The world renders each frame when the world is
  in that state (in the middle of a ``step`` when needed) and queues it (``FrameQueue``).
- Sensor effects on the rendered frame, in this order: blur, contrast, brightness, noise.

No pybullet here: the world passes poses in and gets matrices and images out.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from jetbot_rt.sim.config import SimConfig

URDF_CAMERA_HEIGHT = 0.115
"""m above the floor of jetbot.urdf's camera_link (0.085 m above the 0.03 m axle)."""
URDF_CAMERA_PITCH_DEG = 20.0
"""camera_link's tilt in jetbot.urdf (the JetBot's camera mount)."""
CAMERA_ASPECT = 16 / 9
"""Width/height of the field of view: the real pipeline scales the whole 1280x720 capture to
the policy's size without cropping, so a square frame holds a 16:9 view squeezed sideways."""


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def mount_delta(sim: SimConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """How ``[sim] camera_height`` and ``camera_pitch_deg`` move the camera from jetbot.urdf's
    camera_link, in that link's frame: (offset, rotation); None when they do not (the render
    then uses the link's pose as it is, bit for bit)."""
    if sim.camera_height == URDF_CAMERA_HEIGHT and sim.camera_pitch_deg == URDF_CAMERA_PITCH_DEG:
        return None
    base_up = np.array([0.0, 0.0, sim.camera_height - URDF_CAMERA_HEIGHT])
    offset = _rot_y(math.radians(URDF_CAMERA_PITCH_DEG)).T @ base_up
    rotation = _rot_y(math.radians(sim.camera_pitch_deg - URDF_CAMERA_PITCH_DEG))
    return offset, rotation


class SensorEffects:
    """Blur, contrast, brightness and Gaussian noise on a uint8 RGB frame; a no-op at the
    ideal defaults. The noise comes from a generator seeded with ``[sim] seed``."""

    def __init__(self, sim: SimConfig) -> None:
        self._blur = sim.image_blur
        self._contrast = sim.image_contrast
        self._brightness = sim.image_brightness
        self._noise = sim.image_noise
        self._rng = np.random.default_rng(sim.seed)

    @property
    def ideal(self) -> bool:
        return (self._blur == 0 and self._contrast == 1 and self._brightness == 0
                and self._noise == 0)

    def apply(self, image: np.ndarray) -> np.ndarray:
        if self.ideal:
            return image
        if self._blur > 0:
            sigma = self._blur * image.shape[1]
            image = cv2.GaussianBlur(image, (0, 0), sigmaX=sigma, sigmaY=sigma,
                                     borderType=cv2.BORDER_REFLECT)
        out = image.astype(np.float32)
        if self._contrast != 1 or self._brightness != 0:
            out = (out - 127.5) * self._contrast + 127.5 + 255.0 * self._brightness
        if self._noise > 0:
            noise = self._rng.standard_normal(out.shape, dtype=np.float32)
            noise *= np.float32(255.0 * self._noise)
            out += noise
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)


class FrameQueue:
    """Rendered frames keyed by the sub-step they show, for a camera ``delay`` sub-steps late.

    ``captures(n0, n1)`` lists the sub-steps in ``(n0, n1]`` at which to render, assuming the
    frames are asked for every ``n1 - n0`` sub-steps (the control period) from ``n1`` on;
    ``frame_at(n)`` is the newest frame showing sub-step ``n - delay`` or earlier (before
    sub-step 0 the world stood still in its reset state, which frame 0 shows).
    """

    def __init__(self, delay: int) -> None:
        self.delay = delay
        self._frames: dict[int, np.ndarray] = {}

    def clear(self) -> None:
        self._frames.clear()

    def captures(self, n0: int, n1: int) -> list[int]:
        period = n1 - n0
        if self.delay == 0 or period <= 0:
            return []
        out = []
        delivery = n1
        while delivery - self.delay <= n1:
            capture = delivery - self.delay
            if capture > n0:
                out.append(capture)
            delivery += period
        return sorted(out)

    def put(self, substep: int, image: np.ndarray) -> None:
        self._frames[substep] = image

    def frame_at(self, substep: int) -> np.ndarray | None:
        shown = [k for k in self._frames if k <= substep - self.delay]
        if not shown:
            return self._frames.get(0)
        newest = max(shown)
        for k in [k for k in self._frames if k < newest]:
            del self._frames[k]  # older frames are never delivered again
        return self._frames[newest]
