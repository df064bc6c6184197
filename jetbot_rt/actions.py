"""Policy output -> wheel duties. The one place where speed limit, trim and wiring are applied,
shared by the runtime and the training environment."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from jetbot_rt.errors import Fault

DEFAULT_MAX_SPEED = 0.1


def _clamp(value: float, low: float, high: float) -> float:
    return low if value < low else high if value > high else value


@dataclass(frozen=True)
class ActionPipeline:
    """``duty = clamp(max_speed * clamp(mu, -1, 1) * trim * sign, -1, 1)`` per wheel."""

    max_speed: float = DEFAULT_MAX_SPEED
    trim: tuple[float, float] = (1.0, 1.0)
    sign: tuple[int, int] = (1, 1)

    def duties(self, mu: Sequence[float]) -> tuple[float, float]:
        """Map ``[left, right]`` policy outputs to duties; a non-finite value is a ``Fault``."""
        if len(mu) != 2:
            raise Fault(f"policy gave {len(mu)} action values, expected 2")
        left, right = float(mu[0]), float(mu[1])
        if not (math.isfinite(left) and math.isfinite(right)):
            raise Fault(f"non-finite action mu=[{left}, {right}]")
        return (
            _clamp(self.max_speed * _clamp(left, -1.0, 1.0) * self.trim[0] * self.sign[0], -1, 1),
            _clamp(self.max_speed * _clamp(right, -1.0, 1.0) * self.trim[1] * self.sign[1], -1, 1),
        )


def resolve_max_speed(configured: float | None, from_model: float | None) -> float:
    """Flag or config first, then the model's metadata, then the default."""
    if configured is not None:
        return configured
    if from_model is not None and 0 < from_model <= 1:
        return from_model
    return DEFAULT_MAX_SPEED
