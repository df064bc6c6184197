"""The board's views for ``jetbot-rt calibrate --camera``: taken from the robot's camera while
a person moves the board about in front of it, or read from a directory of frames (the ones a
previous run saved, or any photos the camera took at its full field of view).

Robot side: Python 3.8, numpy and OpenCV only.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from jetbot_rt.calibration.intrinsics import MIN_VIEWS, find_board
from jetbot_rt.config import safe_file
from jetbot_rt.errors import UsageError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
MAX_FILES = 1000
MAX_IMAGE_BYTES = 64 * 1024 * 1024
MIN_MOVE = 0.05
"""A new view's corners must lie this far (mean, as a fraction of the frame's diagonal) from
every view kept: near-copies of one view add nothing to the fit but its weight."""


def moved(a: np.ndarray, b: np.ndarray, size: tuple[int, int]) -> float:
    """Mean distance between the corners of two views, over the frame's diagonal."""
    return float(np.mean(np.linalg.norm(a.reshape(-1, 2) - b.reshape(-1, 2), axis=1))
                 / math.hypot(*size))


def load_frames(directory: str) -> list[np.ndarray]:
    """The images in ``directory`` (png, jpg; sorted by name), RGB; a ``UsageError`` (one
    line) for a directory that is missing or holds no image, an unreadable image, or images
    of different sizes."""
    root = Path(directory)
    if not root.is_dir():
        raise UsageError(f"--frames {directory}: not a directory")
    names = sorted(p.name for p in root.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not names:
        raise UsageError(f"--frames {directory}: no .png or .jpg images in it")
    if len(names) > MAX_FILES:
        raise UsageError(f"--frames {directory}: {len(names)} images, at most {MAX_FILES}")
    images = []
    for name in names:
        data = safe_file.read_bytes(root / name, "frame", MAX_IMAGE_BYTES)
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if image is None or image.ndim != 3 or min(image.shape[:2]) < 16:
            raise UsageError(f"{root / name}: not an image OpenCV can read")
        if images and image.shape != images[0].shape:
            raise UsageError(f"{root / name}: {image.shape[1]}x{image.shape[0]}, the others "
                             f"{images[0].shape[1]}x{images[0].shape[0]} (one camera, one size)")
        images.append(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
    return images


def board_views(images: list[np.ndarray]) -> list[np.ndarray]:
    """The board's corners in each image where the whole board is found."""
    return [c for c in (find_board(image) for image in images) if c is not None]


def enough(views: list[np.ndarray], of: int, where: str) -> None:
    if len(views) < MIN_VIEWS:
        raise UsageError(f"{where}: the board was found in {len(views)} of {of} frames; at "
                         f"least {MIN_VIEWS} are needed (the whole board in view, sharp, moved "
                         "about the frame and tilted)")


def save_frames(directory: Path, images: list[np.ndarray]) -> None:
    """``images`` (RGB) as view-NN.png in a new ``directory``, for ``--frames`` to fit again."""
    try:
        directory.mkdir(parents=True)
        for i, image in enumerate(images):
            ok, data = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            if not ok:
                raise OSError("PNG encoding failed")
            fd = safe_file.create_new(directory / f"view-{i:02d}.png", 0o644)
            try:
                os.write(fd, data.tobytes())
            finally:
                os.close(fd)
    except OSError as exc:
        raise UsageError(f"cannot save the views in {directory}: "
                         f"{exc.strerror or exc}") from None


def collect(read: Callable[[], np.ndarray | None], count: int, time_limit: float,
            size: tuple[int, int], say: Callable[[str], None],
            clock: Callable[[], float] = time.monotonic) -> list[np.ndarray]:
    """Frames from ``read`` (None: no new frame yet) in which the whole board is seen, each at
    least ``MIN_MOVE`` from the others, until ``count`` of them or ``time_limit`` seconds."""
    kept: list[np.ndarray] = []
    corners: list[np.ndarray] = []
    deadline = clock() + time_limit
    while len(kept) < count and clock() < deadline:
        image = read()
        if image is None:
            time.sleep(0.02)
            continue
        found = find_board(image)
        if found is None or any(moved(found, c, size) < MIN_MOVE for c in corners):
            continue
        kept.append(image.copy())
        corners.append(found)
        say(f"view {len(kept)}/{count}: move the board elsewhere (edges and corners too), "
            "tilt it")
    return kept
