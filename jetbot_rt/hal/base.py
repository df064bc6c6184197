"""The two device interfaces every backend implements, and the ``Robot`` that holds them."""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass

import numpy as np

from jetbot_rt.errors import Fault

DEFAULT_FRAME_SIZE = (224, 224)
"""(width, height) of camera frames where no policy says otherwise (the null camera, a bare
``JetbotWorld``, ``check`` without a policy): the rl_games layout's size, which the
JetBot's own examples use. A run takes the size from its policy's ONNX
input; the trainer's size is ``jetbot_rt.train.env.POLICY_IMAGE_SIZE``."""


class NonFinite(Fault, ValueError):
    """A NaN or an infinity where a wheel command is due: a fault while driving (safe stop), a
    ``ValueError`` to callers of the sim world's API."""


def finite_pair(left: float, right: float, what: str = "duty ") -> tuple[float, float]:
    """``(left, right)`` as floats; ``NonFinite`` naming ``what`` if either is NaN or infinite.
    The one non-finite check: the action pipeline, the motor drivers and the sim world call it."""
    left, right = float(left), float(right)
    if not (math.isfinite(left) and math.isfinite(right)):
        raise NonFinite(f"non-finite {what}[{left}, {right}]")
    return left, right


@dataclass(frozen=True)
class Frame:
    """One camera image: ``image`` is HxWx3 uint8 in RGB order; ``t_capture`` is on
    ``time.monotonic()``'s clock (for the sim, the wall time at which it was rendered)."""

    image: np.ndarray
    t_capture: float
    index: int = 0


class Camera(abc.ABC):
    """A camera that keeps only its newest frame."""

    @abc.abstractmethod
    def start(self) -> None:
        """Start capturing; raise ``UsageError`` with the device's own message if it cannot."""

    def cancel_start(self) -> None:  # noqa: B027 - optional hook
        """Make a ``start()`` in progress in another thread give up waiting and return (a
        stop request during start-up). Safe to call at any time, from any thread."""

    @abc.abstractmethod
    def read(self) -> Frame | None:
        """The newest frame, without waiting; None if none has arrived yet."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop capturing and release everything (child processes included). Idempotent."""

    def frame_age(self, frame: Frame, now: float) -> float:
        """How old ``frame`` is at ``now`` (``time.monotonic()``), as ``[loop] max_frame_age``
        judges it: the time the world could move since the image was taken."""
        return now - frame.t_capture


class Drive(abc.ABC):
    """Two wheels. Duties are in [-1, 1]; positive drives the robot forward."""

    @abc.abstractmethod
    def write(self, left: float, right: float) -> None:
        """Apply the duties. Raise ``Fault`` if the hardware cannot be reached."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Turn both motors off by the most direct means the device has."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the device. Called after the final stop."""

    def stats(self) -> dict[str, float]:
        """Counts of faults the device rode through by itself (``i2c_retried``)."""
        return {}


class Robot(abc.ABC):
    """A camera and a drive, and the robot's clock, with a lifecycle: ``connect()`` opens the
    devices (the motor board set up with every output off; the camera stays idle until its
    ``start()``, which the runtime's warm-up calls so that a stop can cancel it), ``step(dt)``
    lets the robot's time pass (simulated time; nothing on hardware, where time passes by
    itself), ``state()`` and ``stats()`` say what it sees and counts, ``disconnect()`` releases
    it. As a context manager: connected inside, motors stopped and disconnected after.

    A subclass builds its camera in ``__init__`` (nothing opened) and opens its drive in
    ``open_drive``.
    """

    simulated = False
    """Whether ``step`` advances a simulated clock (the loop then times it as ``advance_ms``)."""

    def __init__(self, camera: Camera) -> None:
        self.camera = camera
        self._drive: Drive | None = None

    @property
    def connected(self) -> bool:
        return self._drive is not None

    @property
    def drive(self) -> Drive:
        if self._drive is None:
            raise RuntimeError("robot not connected: call connect() first")
        return self._drive

    def connect(self) -> None:
        """Open the devices. Raises ``UsageError`` when one cannot be reached (no motor has
        moved)."""
        if self._drive is None:
            self._drive = self.open_drive()

    @abc.abstractmethod
    def open_drive(self) -> Drive:
        """Open and set up the drive, every output off."""

    def step(self, dt: float) -> None:  # noqa: B027 - a no-op on hardware
        """Let ``dt`` seconds of the robot's time pass. Called once per control period, after
        the tick's write and outside its timing."""

    def state(self) -> dict[str, object]:
        """Fields every tick record carries (the sim's ``pose`` and ``sim_time``, the real
        board's ``i2c_retried``)."""
        return {}

    def stats(self) -> dict[str, float]:
        """For the run's summary and ``end`` event: counts of faults the robot rode through by
        itself (the real board's ``i2c_retried``), what the simulated robot did (the sim's
        ``travelled_m``, ``goal_distance_m``)."""
        return {}

    def disconnect(self) -> None:
        """Stop the camera and release what the robot holds. The drive stays usable for a last
        zero write (the bus closes with the process). Idempotent."""
        self.camera.stop()

    def __enter__(self) -> Robot:
        self.connect()
        return self

    def __exit__(self, *_exc: object) -> None:
        try:
            if self._drive is not None:
                self._drive.stop()
        finally:
            self.disconnect()
