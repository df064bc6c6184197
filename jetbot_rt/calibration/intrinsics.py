"""The camera's lens as ``[sim]`` keys, and its intrinsics measured from a printed checkerboard
(``jetbot-rt calibrate --camera``, docs/CALIBRATION.md).

The model is OpenCV's fisheye model (``cv2.fisheye``): a ray at angle ``theta`` from the
optical axis lands at ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``
from the principal point, in units of the focal length. The keys are normalised by the frame's
size, so that one set of them holds at every size the whole 16:9 capture is scaled to (the
camera pipeline scales without cropping, squeezing it into the policy's square):

- ``lens_focal``: fy / height. fx / width is ``lens_focal / SENSOR_ASPECT`` (square sensor
  pixels); the fit measures both and writes the mean.
- ``lens_center``: (cx / width, cy / height), pixel edges at 0 and 1.
- ``lens_k1`` .. ``lens_k4``.

Robot side: Python 3.8, numpy and OpenCV only. The simulator's renderer (``sim/lens.py``) uses
the same ``Lens`` so that the sim and the calibration cannot disagree on the model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from jetbot_rt.errors import UsageError

SENSOR_ASPECT = 16 / 9
"""Width / height of the camera's field of view: the IMX219's 1280x720 mode."""
MAX_ANGLE_DEG = 80.0
"""The widest ray a frame may hold: the simulator renders a pinhole under the fisheye, whose
size grows as tan(angle) (at 80 degrees 5.7 focal lengths from the centre)."""
BOARD_INNER = (9, 6)
"""Inner corners (columns, rows) of the printed board, jetbot_rt/data/checkerboard-9x6.png."""
BOARD_SQUARE = 0.025
"""m: the printed board's square at 100 % on A4 (10 x 7 squares, 250 x 175 mm)."""
MIN_VIEWS = 6
FISHEYE_FLAGS_4X = {"CALIB_USE_INTRINSIC_GUESS": 1, "CALIB_RECOMPUTE_EXTRINSIC": 2,
                    "CALIB_FIX_SKEW": 8}
"""cv2.fisheye's flags as OpenCV 4.x numbers them, for a build that names them nowhere."""


def fisheye_flags() -> int:
    """cv2.fisheye.calibrate's flags (the intrinsic guess, the poses recomputed, no skew) as
    this OpenCV numbers them: 4.x names them at cv2.fisheye.CALIB_* or cv2.CALIB_* depending
    on the build (JetPack's 4.1 and the pip wheels differ), 5.x at cv2.CALIB_* with other
    values (4.x's 2 and 8 mean other flags there: OpenCV's stage then kept the skew and the
    first poses)."""
    fisheye = getattr(cv2, "fisheye", None)
    flags = 0
    for name, value in FISHEYE_FLAGS_4X.items():
        named = getattr(fisheye, name, None) if fisheye is not None else None
        flags |= int(named if named is not None else getattr(cv2, name, value))
    return flags


@dataclass(frozen=True)
class Lens:
    """A fisheye lens in the ``[sim]`` keys' units."""

    focal: float = 1.0194
    center: tuple[float, float] = (0.5, 0.5)
    k: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    @classmethod
    def from_sim(cls, sim: Any) -> Lens:
        return cls(float(sim.lens_focal), (float(sim.lens_center[0]), float(sim.lens_center[1])),
                   (float(sim.lens_k1), float(sim.lens_k2), float(sim.lens_k3),
                    float(sim.lens_k4)))

    def matrix(self, width: int, height: int) -> np.ndarray:
        """OpenCV's camera matrix for a frame of ``width`` x ``height`` (pixel centres on
        integers, as OpenCV has them)."""
        fy = self.focal * height
        fx = self.focal / SENSOR_ASPECT * width
        return np.array([[fx, 0.0, self.center[0] * width - 0.5],
                         [0.0, fy, self.center[1] * height - 0.5], [0.0, 0.0, 1.0]])

    def distortion(self) -> np.ndarray:
        return np.array(self.k, dtype=np.float64).reshape(4, 1)

    def distort_angle(self, theta: np.ndarray) -> np.ndarray:
        t2 = theta * theta
        k1, k2, k3, k4 = self.k
        return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def undistort_angle(self, theta_d: np.ndarray, width: int, height: int) -> np.ndarray:
        """The ray's angle for each image angle ``theta_d``; a ``UsageError`` when the frame
        (``width`` x ``height``) holds an image angle that no ray below ``MAX_ANGLE_DEG``
        gives, or the model folds back (theta_d not increasing) before its corners."""
        grid = np.linspace(0.0, math.radians(MAX_ANGLE_DEG), 4001)
        table = self.distort_angle(grid)
        rising = np.diff(table) > 0
        last = len(grid) - 1 if rising.all() else int(np.argmin(rising))
        reach = float(table[last])
        widest = float(np.max(theta_d))
        if widest > reach:
            folds = last < len(grid) - 1
            why = (f"its distortion folds back at {math.degrees(grid[last]):.0f} degrees"
                   if folds else f"a ray at {MAX_ANGLE_DEG:g} degrees, the most the sim "
                   "renders, lands inside the frame")
            raise UsageError(
                f"[sim] lens: this lens (lens_focal {self.focal:g}, lens_k1..k4 "
                f"{list(self.k)}) cannot fill a {width}x{height} frame: {why}")
        theta = np.interp(theta_d, table[:last + 1], grid[:last + 1])
        k = np.array(self.k)
        for _ in range(3):  # Newton: the table is close, these make it exact
            t2 = theta * theta
            slope = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
            theta = theta - (self.distort_angle(theta) - theta_d) / slope
        return theta

    def rays(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """For each pixel centre of a ``width`` x ``height`` frame, where its ray meets the
        plane z = 1 (OpenCV's camera frame: x right, y down): (x, y), each (height, width)."""
        m = self.matrix(width, height)
        xd = (np.arange(width, dtype=np.float64) - m[0, 2]) / m[0, 0]
        yd = (np.arange(height, dtype=np.float64) - m[1, 2]) / m[1, 1]
        xd, yd = np.meshgrid(xd, yd)
        theta_d = np.hypot(xd, yd)
        theta = self.undistort_angle(theta_d, width, height)
        scale = np.where(theta_d > 1e-12, np.tan(theta) / np.maximum(theta_d, 1e-12), 1.0)
        return xd * scale, yd * scale


def radial_error_px(truth: Lens, fitted: Lens, width: int = 640,
                    height: int = 360) -> tuple[float, float]:
    """The largest difference in image radius (px) between the two lenses for rays out to the
    truth's side edge and out to its corner."""
    out = []
    matrix = truth.matrix(width, height)
    for dx, dy in ((width / 2, 0.0), (width / 2, height / 2)):
        widest = math.hypot(dx / matrix[0, 0], dy / matrix[1, 1])
        theta = float(truth.undistort_angle(np.array([widest]), width, height)[0])
        grid = np.linspace(0.0, theta, 200)
        out.append(float(np.abs(fitted.focal * height * fitted.distort_angle(grid)
                                - truth.focal * height * truth.distort_angle(grid)).max()))
    return out[0], out[1]


def board_png() -> Path:
    """The printable board: 10 x 7 squares (9 x 6 inner corners) and a white margin."""
    return Path(__file__).resolve().parents[1] / "data" / "checkerboard-9x6.png"


def board_points(inner: tuple[int, int] = BOARD_INNER, square: float = BOARD_SQUARE) -> np.ndarray:
    """The inner corners on the board's plane, in findChessboardCorners' order (row by row),
    (1, n, 3) float64 as cv2.fisheye.calibrate wants them."""
    cols, rows = inner
    grid = np.zeros((1, rows * cols, 3), np.float64)
    grid[0, :, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square
    return grid


def find_board(image: np.ndarray, inner: tuple[int, int] = BOARD_INNER) -> np.ndarray | None:
    """The board's inner corners in ``image`` (RGB or grey), (1, n, 2) float64, or None when
    the whole board is not seen. ``findChessboardCornersSB``: a localised fit of each corner,
    more accurate than the classic detector and robust to the lens's curvature."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCornersSB(grey, inner, flags=flags)
    if not found or corners is None or len(corners) != inner[0] * inner[1]:
        return None
    return corners.reshape(1, -1, 2).astype(np.float64)


@dataclass(frozen=True)
class Fit:
    lens: Lens
    fx_over_width: float
    """fx / width times SENSOR_ASPECT: equal to ``lens.focal`` for square sensor pixels."""
    fy_over_height: float
    rms_px: float
    views: int
    size: tuple[int, int]
    k_sigma: tuple[float, float, float, float]
    focal_sigma: float


def calibrate(views: Sequence[np.ndarray], size: tuple[int, int],
              inner: tuple[int, int] = BOARD_INNER, square: float = BOARD_SQUARE) -> Fit:
    """Fit the lens to the board's corners seen in ``views`` (each ``find_board``'s output) in
    frames of ``size`` (width, height): cv2.fisheye.calibrate from the datasheet's lens (skew
    fixed at 0), then a joint Levenberg-Marquardt refinement of the intrinsics and every view's
    pose (what OpenCV's fit leaves, the refinement takes to float round-off on exact synthetic
    corners: ``benchmarks/bench_calibration.py``). A ``ValueError`` when the views are too few
    or the fit does not converge."""
    if len(views) < MIN_VIEWS:
        raise ValueError(f"{len(views)} views of the board; at least {MIN_VIEWS} are needed "
                         "(the board tilted and moved about the whole frame)")
    width, height = size
    board = board_points(inner, square)
    objects = [board] * len(views)
    flags = fisheye_flags()
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    try:
        _, matrix, dist, rvecs, tvecs = cv2.fisheye.calibrate(
            objects, list(views), (width, height), Lens().matrix(width, height),
            np.zeros((4, 1)), flags=flags, criteria=criteria)
    except cv2.error as exc:
        first = str(exc).strip().splitlines()[-1] if str(exc).strip() else "cv2.error"
        raise ValueError(f"the fisheye fit failed ({first}): views too alike, or the board "
                         "misdetected") from None
    start = np.array([matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2],
                      *np.ravel(dist)], dtype=np.float64)
    poses = np.array([[*np.ravel(r), *np.ravel(t)] for r, t in zip(rvecs, tvecs)])
    q, rms, sigma = _refine(board, [np.asarray(v, np.float64) for v in views], start, poses)
    q = [float(v) for v in q]
    fx_w = q[0] / width * SENSOR_ASPECT
    fy_h = q[1] / height
    lens = Lens((fx_w + fy_h) / 2, ((q[2] + 0.5) / width, (q[3] + 0.5) / height),
                (q[4], q[5], q[6], q[7]))
    if not all(math.isfinite(v) for v in (lens.focal, *lens.center, *lens.k, rms)):
        raise ValueError("the fisheye fit diverged (non-finite values)")
    focal_sigma = math.hypot(sigma[0] / width * SENSOR_ASPECT, sigma[1] / height) / 2
    return Fit(lens, fx_w, fy_h, rms, len(views), (width, height),
               (sigma[4], sigma[5], sigma[6], sigma[7]), focal_sigma)


def _project(board: np.ndarray, q: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The board's corners seen from ``pose`` (rvec, tvec) through intrinsics ``q`` (fx, fy,
    cx, cy, k1..k4), (2n,), and their Jacobian in (q, pose), (2n, 14)."""
    matrix = np.array([[q[0], 0.0, q[2]], [0.0, q[1], q[3]], [0.0, 0.0, 1.0]])
    points, jac = cv2.fisheye.projectPoints(board, pose[:3].reshape(3, 1), pose[3:].reshape(3, 1),
                                            matrix, q[4:8].reshape(4, 1))
    # OpenCV's columns: f (2), c (2), k (4), rvec (3), tvec (3), skew (1)
    return points.reshape(-1), np.asarray(jac)[:, :14]


def _refine(board: np.ndarray, views: list[np.ndarray], q: np.ndarray,
            poses: np.ndarray) -> tuple[np.ndarray, float, list[float]]:
    """Levenberg-Marquardt over the intrinsics and all poses together; the intrinsics, the rms
    reprojection error (px) and the intrinsics' standard errors."""
    n = len(views)
    seen = np.concatenate([v.reshape(-1) for v in views])
    rows = seen.size // n

    def evaluate(q: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        jac = np.zeros((seen.size, 8 + 6 * n))
        res = np.empty(seen.size)
        for i in range(n):
            points, j = _project(board, q, poses[i])
            block = slice(i * rows, (i + 1) * rows)
            res[block] = points
            jac[block, :8] = j[:, :8]
            jac[block, 8 + 6 * i:14 + 6 * i] = j[:, 8:14]
        return res - seen, jac

    res, jac = evaluate(q, poses)
    cost = float(res @ res)
    damping = 1e-3
    for _ in range(100):
        normal = jac.T @ jac
        grad = jac.T @ res
        try:
            step = np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-12), -grad)
        except np.linalg.LinAlgError:
            break
        q_new, poses_new = q + step[:8], poses + step[8:].reshape(n, 6)
        res_new, jac_new = evaluate(q_new, poses_new)
        cost_new = float(res_new @ res_new)
        if math.isfinite(cost_new) and cost_new < cost:
            done = cost - cost_new < 1e-12 * cost
            q, poses, res, jac, cost = q_new, poses_new, res_new, jac_new, cost_new
            damping = max(damping / 3, 1e-9)
            if done:
                break
        else:
            damping *= 5
            if damping > 1e8:
                break
    dof = max(seen.size - (8 + 6 * n), 1)
    try:
        cov = np.linalg.inv(jac.T @ jac) * (cost / dof)
        sigma = [float(math.sqrt(max(v, 0.0))) for v in np.diag(cov)[:8]]
    except np.linalg.LinAlgError:
        sigma = [math.nan] * 8
    return q, math.sqrt(cost / seen.size * 2), sigma


def to_toml(fit: Fit, source: str) -> str:
    """The ``[sim]`` lens keys of ``fit``, with its uncertainties as comments."""
    lens = fit.lens
    ks = "\n".join(f"lens_k{i + 1} = {lens.k[i]:.5f}  # +- {fit.k_sigma[i]:.5f}"
                   for i in range(4))
    return (
        f"# jetbot-rt calibrate --camera: {fit.views} views of the board in {source}, "
        f"{fit.size[0]}x{fit.size[1]}\n"
        f"# reprojection rms {fit.rms_px:.3f} px; the +- are standard errors (the views "
        "taken as independent: optimistic)\n"
        "[sim]\n"
        'lens = "fisheye"\n'
        f"lens_focal = {lens.focal:.5f}  # +- {fit.focal_sigma:.5f}; fy/height "
        f"{fit.fy_over_height:.5f}, fx/width x 16/9 {fit.fx_over_width:.5f}\n"
        f"lens_center = [{lens.center[0]:.5f}, {lens.center[1]:.5f}]\n"
        f"{ks}\n"
    )
