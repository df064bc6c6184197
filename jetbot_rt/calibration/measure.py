"""What the camera measures: the printed ArUco marker's centre, as a horizontal range and a
bearing from the camera, from its four corners and its known size (OpenCV's aruco module and
``solvePnP``). Only the marker's position is used, never its estimated orientation: a small
square's orientation is ambiguous (two poses fit nearly equally well), its position is not."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from jetbot_rt.calibration.intrinsics import SENSOR_ASPECT, Lens

MARKER_DICT = cv2.aruco.DICT_4X4_50
MARKER_ID = 7


def marker_png() -> Path:
    """The printable page: marker id 7 of DICT_4X4_50 and one white cell around it."""
    return Path(__file__).resolve().parents[1] / "data" / "aruco-4x4-id7.png"


@dataclass(frozen=True)
class Geometry:
    """What the fit and the measurement need to know of the robot and the marker (metres)."""

    marker_size: float = 0.10
    """The marker's black square, edge to edge, as printed."""
    marker_height: float = 0.0667
    """The marker's centre above the floor (the page standing on the floor: 2/3 of its size)."""
    camera_height: float = 0.115
    camera_offset: float = 0.06
    """The camera ahead of the wheel axle."""
    wheel_radius: float = 0.03
    track: float = 0.11
    vfov_deg: float = 52.0
    """The pinhole's vertical field of view over the 16:9 sensor ([sim] camera_vfov_deg)."""
    lens_focal: float = 0.0
    """0: the camera is the pinhole above; else the fisheye of ``[sim] lens_focal``,
    ``lens_center`` (``lens_cx``, ``lens_cy``) and ``lens_k1``..``lens_k4``."""
    lens_cx: float = 0.5
    lens_cy: float = 0.5
    lens_k1: float = 0.0
    lens_k2: float = 0.0
    lens_k3: float = 0.0
    lens_k4: float = 0.0

    def lens(self) -> Lens | None:
        if self.lens_focal <= 0:
            return None
        return Lens(self.lens_focal, (self.lens_cx, self.lens_cy),
                    (self.lens_k1, self.lens_k2, self.lens_k3, self.lens_k4))


def camera_matrix(width: int, height: int, vfov_deg: float) -> np.ndarray:
    """A pinhole over the 16:9 field of view, scaled to a frame of ``width`` x ``height`` (the
    pixels are not square when the frame is not 16:9, as the sim's and the gst pipeline's)."""
    tan_v = math.tan(math.radians(vfov_deg) / 2)
    fx = (width / 2) / (SENSOR_ASPECT * tan_v)
    fy = (height / 2) / tan_v
    # OpenCV puts pixel centres on integers: the image centre is (width - 1) / 2
    return np.array([[fx, 0, (width - 1) / 2], [0, fy, (height - 1) / 2], [0, 0, 1]],
                    dtype=np.float64)


class MarkerMeter:
    """Finds the marker in a frame; ``measure`` gives (range m, bearing rad, right positive)."""

    def __init__(self, geometry: Geometry, frame_size: tuple[int, int]) -> None:
        self.geometry = geometry
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._detector = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(MARKER_DICT), params)
        self._lens = geometry.lens()
        if self._lens is None:
            self._matrix = camera_matrix(frame_size[0], frame_size[1], geometry.vfov_deg)
        else:  # the corners are undistorted to the plane z = 1 first: a unit pinhole
            self._fisheye = (self._lens.matrix(*frame_size), self._lens.distortion())
            self._matrix = np.eye(3)
        half = geometry.marker_size / 2
        self._object = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0],
                                 [-half, -half, 0]], dtype=np.float64)

    def measure(self, image: np.ndarray) -> tuple[float, float] | None:
        corners, ids, _ = self._detector.detectMarkers(image)
        if ids is None:
            return None
        found = [c for c, i in zip(corners, ids.ravel()) if i == MARKER_ID]
        if len(found) != 1:
            return None
        points = found[0].reshape(4, 2).astype(np.float64)
        if self._lens is not None:
            points = cv2.fisheye.undistortPoints(points.reshape(1, 4, 2), *self._fisheye)
            points = points.reshape(4, 2).astype(np.float64)
        ok, _rvec, tvec = cv2.solvePnP(self._object, points, self._matrix, None,
                                       flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if not ok:
            return None
        tx, ty, tz = (float(v) for v in tvec.ravel())
        drop = self.geometry.marker_height - self.geometry.camera_height
        horizontal = tx * tx + ty * ty + tz * tz - drop * drop
        if horizontal <= tx * tx or not math.isfinite(horizontal):
            return None
        reach = math.sqrt(horizontal)
        return reach, math.asin(tx / reach)
