"""The two device interfaces every backend implements, and the bundle the loop drives."""

from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

DEFAULT_FRAME_SIZE = (224, 224)
"""(width, height) of camera frames where no policy says otherwise: the input of the first
bundled policy (forward.onnx). A run takes the size from its policy's ONNX input; the trainer's
size is ``jetbot_rt.train.env.POLICY_IMAGE_SIZE``."""


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


@dataclass
class Backend:
    """What ``make_backend`` returns: a camera, a drive, and an optional per-tick hook.

    ``advance(dt)`` runs after the drive write of each tick: the sim steps its world by one
    control period and renders the next frame; real hardware has no hook.
    """

    camera: Camera
    drive: Drive
    advance: Callable[[float], None] | None = None
    close: Callable[[], None] = field(default=lambda: None)
    telemetry: Callable[[], dict[str, object]] | None = None
    """Extra per-tick telemetry fields (the sim adds the robot's ``pose``)."""
    counters: Callable[[], dict[str, float]] | None = None
    """Added to the run summary and the ``end`` event: counts of faults the backend rode
    through by itself (the real backend's ``i2c_retried``), what the simulated robot did (the
    sim's ``travelled_m``, ``goal_distance_m``)."""
