"""The drive programme: a fixed list of duty steps, played by ``jetbot-rt run``'s control loop
in place of a policy (``Programme.infer`` gives each tick's duties), with the marker watched on
every frame: the robot stops (a fault, exit 3) when the marker is lost or it leaves the area.

Every step out is followed by the same step back, so the robot ends near where it started
(exactly, for a robot whose wheels behave the same forwards and backwards): single-wheel steps
at a third, two thirds and all of ``max_duty`` on each wheel (gain and dead-band per wheel),
a straight run out and back (latency, the time constant), a turn on the spot each way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Tuple

import cv2
import numpy as np

from jetbot_rt.calibration.measure import Geometry, MarkerMeter
from jetbot_rt.errors import Fault

Step = Tuple[float, float, float]
"""(left duty, right duty, seconds)."""

SETTLE_S = 0.6
"""Standing still at the start (the first sightings of the marker) and after each step."""
STEP_S = 0.25
"""Each step out (and back): at 0.3 duty on one wheel the sim's robot turns about 25 degrees."""


def steps(max_duty: float) -> list[Step]:
    out: list[Step] = [(0.0, 0.0, SETTLE_S)]

    def there_and_back(left: float, right: float, seconds: float = STEP_S) -> None:
        out.extend([(left, right, seconds), (0.0, 0.0, SETTLE_S / 2),
                    (-left, -right, seconds), (0.0, 0.0, SETTLE_S / 2)])

    for level in (1 / 3, 2 / 3, 1.0):
        there_and_back(level * max_duty, 0.0)
        there_and_back(0.0, level * max_duty)
    there_and_back(max_duty, max_duty, 2 * STEP_S)
    there_and_back(-max_duty / 2, max_duty / 2)
    there_and_back(max_duty / 2, -max_duty / 2)
    return out


def duration(max_duty: float) -> float:
    return sum(s for _, _, s in steps(max_duty))


@dataclass(frozen=True)
class Limits:
    max_duty: float = 0.3
    max_travel: float = 0.25
    """Metres the marker's range may change from the start before the robot stops."""
    max_bearing_deg: float = 35.0
    lost_s: float = 0.5
    """The marker unseen this long (once driving): stop."""


@dataclass(frozen=True)
class Spec:
    """The frame size the policy's ``InputSpec`` would give, as the phases read it."""

    width: int
    height: int


class Programme:
    """Looks like an ``OnnxPolicy`` to the run's phases (``spec``, ``max_speed``,
    ``calibrated``, ``metadata``, ``path``, ``fit``, ``describe``, ``infer``) and plays
    ``steps`` once ``arm``ed; before that (warm-up) it only checks that the marker is in
    view."""

    max_speed = 1.0
    calibrated = False
    """It drives raw duties (``calibrate`` sets ``[actions] deadband`` to 0): no lift."""

    def __init__(self, geometry: Geometry, limits: Limits, frame_size: tuple[int, int],
                 rate_hz: float) -> None:
        self.geometry = geometry
        self.limits = limits
        self.spec = Spec(*frame_size)
        self.period = 1.0 / rate_hz
        self.path = Path(__file__)
        self.meter = MarkerMeter(geometry, frame_size)
        self._steps = steps(limits.max_duty)
        self._ends = np.cumsum([s for _, _, s in self._steps])
        self.metadata: dict[str, str] = {"jetbot_rt.calibration": repr(self.describe())}
        self._clock: Callable[[], float] | None = None
        self._t0 = 0.0
        self._start_range: float | None = None
        self._last_seen = 0.0
        self._done: Callable[[], None] = lambda: None

    def describe(self) -> dict[str, object]:
        return {"programme": "calibrate", "geometry": vars(self.geometry),
                "limits": vars(self.limits), "frame_size": [self.spec.width, self.spec.height]}

    def fit(self, image: np.ndarray) -> np.ndarray:
        return cv2.resize(image, (self.spec.width, self.spec.height),
                          interpolation=cv2.INTER_AREA)

    def arm(self, simulated: bool, done: Callable[[], None]) -> None:
        """From now on ``infer`` plays the steps; time counts ticks in the simulation (a late
        tick there is no lost time), the monotonic clock on the robot."""
        if simulated:
            ticks = [0]

            def clock() -> float:
                ticks[0] += 1
                return (ticks[0] - 1) * self.period

            self._clock = clock
        else:
            self._clock = time.monotonic
        self._t0 = self._clock()
        self._last_seen = 0.0
        self._done = done

    def command(self, t: float) -> tuple[float, float]:
        index = int(np.searchsorted(self._ends, t, side="right"))
        if index >= len(self._steps):
            return (0.0, 0.0)
        left, right, _ = self._steps[index]
        return (left, right)

    def infer(self, image: np.ndarray) -> np.ndarray:
        if image.shape[1::-1] != (self.spec.width, self.spec.height):
            image = self.fit(image)
        seen = self.meter.measure(image)
        if self._clock is None:  # warm-up: the robot stands still
            if seen is None:
                raise ValueError("no calibration marker in view (id 7 of ArUco DICT_4X4_50, "
                                 "docs/CALIBRATION.md)")
            return np.zeros(2, dtype=np.float32)
        t = self._clock() - self._t0
        if t >= self._ends[-1]:
            self._done()  # an orderly end: the run's stop phase follows
        self._watch(t, seen)
        return np.array(self.command(t), dtype=np.float32)

    def _watch(self, t: float, seen: tuple[float, float] | None) -> None:
        limits = self.limits
        if seen is None:
            if t - self._last_seen > limits.lost_s:
                raise Fault(f"calibration marker lost for {limits.lost_s:g} s")
            return
        self._last_seen = t
        reach, bearing = seen
        if self._start_range is None:
            self._start_range = reach
        if abs(reach - self._start_range) > limits.max_travel:
            raise Fault(f"left the area: the marker's range changed by "
                        f"{reach - self._start_range:+.2f} m (limit {limits.max_travel:g} m)")
        if abs(np.degrees(bearing)) > limits.max_bearing_deg:
            raise Fault(f"left the area: the marker is {np.degrees(bearing):+.0f} degrees off "
                        f"the camera's axis (limit {limits.max_bearing_deg:g})")
