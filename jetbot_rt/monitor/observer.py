"""What the monitor knows of the run: the loop's observer keeps a reference to the newest
``TickResult`` and nothing else, so a tick pays one attribute store for the page (no lock, no
copy, no encoding; the frame is the camera's own array, never written again). Everything the
page shows is computed from it in the server's threads, when a client asks.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import TYPE_CHECKING, Any, Callable

import cv2
import numpy as np

if TYPE_CHECKING:
    from jetbot_rt.recording.recorder import Recorder
    from jetbot_rt.runtime.loop import LoopStats, TickResult
    from jetbot_rt.runtime.safety import SafeStopLatch

TRAJECTORY_POINTS = 3000
"""The sim's path kept for the page: 5 minutes at 10 samples a second."""
JPEG_QUALITY = 85
VIEWS = ("prepared", "raw")


class RunView:
    """The run as the page sees it. ``observe`` is the loop's tick observer."""

    def __init__(self, latch: SafeStopLatch, stats: LoopStats, rate_hz: float, t0: float,
                 fit: Callable[[np.ndarray], np.ndarray] | None = None, bgr_model: bool = False,
                 recorder: Recorder | None = None) -> None:
        self.latch = latch
        self.stats = stats
        self.rate_hz = rate_hz
        self.t0 = t0
        self.fit = fit
        self.bgr_model = bgr_model
        self.recorder = recorder
        self.latest: TickResult | None = None
        self.ended: dict[str, Any] | None = None
        self.trajectory: collections.deque[tuple[float, float]] = collections.deque(
            maxlen=TRAJECTORY_POINTS)
        self.measured_hz = 0.0
        self._rate_sample: tuple[float, int] | None = None
        self._jpeg_lock = threading.Lock()
        self._jpeg: dict[str, tuple[int, bytes]] = {}

    # ---- the control thread -------------------------------------------------------------

    def observe(self, result: TickResult) -> None:
        self.latest = result

    # ---- the server's threads ------------------------------------------------------------

    def sample(self) -> None:
        """Called a few times a second by the server: the measured rate and the sim's path."""
        now, ticks = time.monotonic(), self.stats.ticks
        if self._rate_sample is not None:
            t_prev, ticks_prev = self._rate_sample
            if now - t_prev >= 1.0:
                self.measured_hz = (ticks - ticks_prev) / (now - t_prev)
                self._rate_sample = (now, ticks)
        else:
            self._rate_sample = (now, ticks)
        latest = self.latest
        pose = latest.extra.get("pose") if latest is not None else None
        if isinstance(pose, list) and len(pose) >= 2:
            point = (round(float(pose[0]), 3), round(float(pose[1]), 3))
            if not self.trajectory or self.trajectory[-1] != point:
                self.trajectory.append(point)

    def phase(self) -> tuple[str, str | None]:
        """(state, reason): starting, driving, stopping, safe stop, ended."""
        if self.ended is not None:
            return "ended", self.latch.reason
        if self.latch.tripped:
            return ("safe stop" if self.latch.fault else "stopping"), self.latch.reason
        if self.latest is None:
            return "warming up", None
        return "driving", None

    def state(self, stream: dict[str, int], trajectory: bool = True) -> dict[str, Any]:
        """``GET /state``: the last tick's record and the run's state, one JSON object."""
        latest = self.latest
        state, reason = self.phase()
        stats = self.stats
        out: dict[str, Any] = {
            "state": state, "reason": reason, "fault": self.latch.fault,
            "target_hz": self.rate_hz, "measured_hz": round(self.measured_hz, 2),
            "ticks": stats.ticks, "overruns": stats.overruns,
            "tick_ms_p99": round(stats.tick_ms.percentile(99), 3) if stats.ticks else None,
            "stream": dict(stream),
        }
        if latest is not None:
            out["record"] = latest.record(self.t0)
            out["frame_index"] = latest.frame_index
        if self.recorder is not None:
            out["recording"] = self.recorder.counts()
        if trajectory and self.trajectory:
            out["trajectory"] = list(self.trajectory)
            goal = latest.extra.get("goal") if latest is not None else None
            if isinstance(goal, list) and len(goal) == 2:
                out["goal"] = goal
        if self.ended is not None:
            out["ended"] = self.ended
        return out

    def jpeg(self, view: str) -> tuple[int, bytes] | None:
        """(tick, JPEG) of the newest frame in ``view``: encoded at most once per tick and
        view, however many clients ask."""
        latest = self.latest
        if latest is None:
            return None
        with self._jpeg_lock:
            cached = self._jpeg.get(view)
            if cached is not None and cached[0] == latest.tick:
                return cached
            image = latest.image
            if view == "prepared" and self.fit is not None:
                image = self.fit(image)
                if self.bgr_model:
                    image = image[:, :, ::-1]  # shown as the model reads it
            ok, data = cv2.imencode(".jpg", np.ascontiguousarray(image[:, :, ::-1]),
                                    [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:  # pragma: no cover - a uint8 HxWx3 image always encodes
                return None
            encoded = (latest.tick, data.tobytes())
            self._jpeg[view] = encoded
            return encoded
