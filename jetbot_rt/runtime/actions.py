"""Policy output -> wheel duties. The one place where speed limit, trim and wiring are applied,
shared by the runtime and the training environment."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from jetbot_rt.errors import Fault
from jetbot_rt.hal.base import finite_pair

if TYPE_CHECKING:
    from jetbot_rt.config.sections import ActionsConfig

DEFAULT_MAX_SPEED = 0.1


def _clamp(value: float, low: float, high: float) -> float:
    return low if value < low else high if value > high else value


@dataclass(frozen=True)
class ActionPipeline:
    """``d = max_speed * clamp(mu, -1, 1) * trim * sign`` per wheel, then a duty that is not
    zero lifted by ``deadband``, ``sign(d) * (|d| + deadband)``, and clamped to [-1, 1]."""

    max_speed: float = DEFAULT_MAX_SPEED
    trim: tuple[float, float] = (1.0, 1.0)
    sign: tuple[int, int] = (1, 1)
    deadband: float = 0.0

    @classmethod
    def from_config(cls, actions: ActionsConfig, model_max_speed: float | None = None
                    ) -> ActionPipeline:
        """The pipeline of ``[actions]`` (flags included) and the model's ``max_speed``
        metadata: the one builder, for the runtime and the training environment."""
        return cls(
            max_speed=resolve_max_speed(actions.max_speed, model_max_speed),
            trim=(float(actions.trim[0]), float(actions.trim[1])),
            sign=(int(actions.sign[0]), int(actions.sign[1])),
            deadband=float(actions.deadband),
        )

    def duties(self, mu: Sequence[float]) -> tuple[float, float]:
        """Map ``[left, right]`` policy outputs to duties; a non-finite value is a ``Fault``."""
        if len(mu) != 2:
            raise Fault(f"policy gave {len(mu)} action values, expected 2")
        left, right = finite_pair(mu[0], mu[1], "action mu=")
        return (
            self._lifted(self.max_speed * _clamp(left, -1.0, 1.0) * self.trim[0] * self.sign[0]),
            self._lifted(self.max_speed * _clamp(right, -1.0, 1.0) * self.trim[1] * self.sign[1]),
        )

    def _lifted(self, duty: float) -> float:
        # A motor whose friction takes ``deadband`` of its duty turns at a speed proportional
        # to |duty| - deadband; lifting every duty that is not zero by it gives back a speed
        # proportional to the command. Zero stays zero: a stop is never lifted.
        if duty > 0.0:
            duty += self.deadband
        elif duty < 0.0:
            duty -= self.deadband
        return _clamp(duty, -1.0, 1.0)


def resolve_max_speed(configured: float | None, from_model: float | None) -> float:
    """Flag or config first, then the model's metadata, then the default."""
    if configured is not None:
        return configured
    if from_model is not None and 0 < from_model <= 1:
        return from_model
    return DEFAULT_MAX_SPEED
