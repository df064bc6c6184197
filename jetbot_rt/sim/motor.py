"""The wheel motors: what a duty written to the motor board does to each wheel.

Per wheel and per physics sub-step (docs/SIM.md, "Motor model"):

1. command latency: a duty written at sub-step ``k`` acts from sub-step ``k + L`` on,
   ``L = round([sim] latency * physics_hz)`` (a queue of timestamped commands);
2. dead-band and gain: the steady speed is ``motor_gain * wheel_gain * sign(d) *
   max(|d| - deadband, 0)`` rad/s, the speed of a DC motor whose friction takes
   ``deadband`` of its torque;
3. a first-order lag (``motor_tau``) on that speed, the target of PyBullet's velocity motor;
4. the torque the velocity motor may use: the ideal motor's constant 0.15 N m, or, with
   ``stall_torque`` set, a DC motor's torque at this duty and speed,
   ``stall * (d - omega / omega_0)`` less friction, so torque scales with duty.

Pure Python: the world feeds it measured wheel speeds and applies what it returns.
"""

from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from jetbot_rt.sim.config import SimConfig

IDEAL_TORQUE = 0.15
"""N m per wheel: the ideal motor's force limit at any duty (about a small 1:48 gear motor's
stall torque at 5-6 V; docs/SIM.md)."""


class WheelMotors:
    """Both wheel motors of one world; ``reset()`` at each episode."""

    def __init__(self, sim: SimConfig) -> None:
        self._hz = sim.physics_hz
        self._omega0 = (sim.motor_gain * sim.wheel_gain[0], sim.motor_gain * sim.wheel_gain[1])
        self._deadband = sim.deadband
        self._delay = round(sim.latency * sim.physics_hz)
        # exact discretisation of d(omega)/dt = (target - omega) / tau over one sub-step
        tau = sim.motor_tau
        self._blend = 1.0 if tau == 0 else -math.expm1(-1.0 / (sim.physics_hz * tau))
        self._stall = (
            None if sim.stall_torque is None
            else (sim.stall_torque * sim.wheel_gain[0], sim.stall_torque * sim.wheel_gain[1])
        )
        self.reset()

    @property
    def needs_wheel_speed(self) -> bool:
        """True when ``substep`` reads the measured wheel speeds (the DC-motor torque)."""
        return self._stall is not None

    def reset(self) -> None:
        self._queue: deque[tuple[int, tuple[float, float]]] = deque()
        self._duty = (0.0, 0.0)
        self._omega = [0.0, 0.0]  # the lagged velocity targets, rad/s

    def command(self, substep: int, left: float, right: float) -> None:
        """A duty pair written at sub-step index ``substep``; acts after the latency."""
        self._queue.append((substep + self._delay, (left, right)))

    def substep(
        self, k: int, measured: tuple[float, float] | None
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        """Target velocities (rad/s) and force limits (N m) for sub-step ``k`` -> ``k + 1``.
        ``measured``: the wheels' speeds now (only read when ``needs_wheel_speed``)."""
        while self._queue and self._queue[0][0] <= k:
            self._duty = self._queue.popleft()[1]
        targets, forces = [0.0, 0.0], [IDEAL_TORQUE, IDEAL_TORQUE]
        for i in (0, 1):
            d = self._duty[i]
            steady = math.copysign(self._omega0[i] * max(abs(d) - self._deadband, 0.0), d)
            self._omega[i] += self._blend * (steady - self._omega[i])
            targets[i] = self._omega[i]
            if self._stall is not None:
                forces[i] = self._dc_torque(i, measured[i] if measured else 0.0)
        return (targets[0], targets[1]), (forces[0], forces[1])

    def _dc_torque(self, i: int, omega: float) -> float:
        """A DC motor's net torque towards the target: ``stall / omega_0`` per rad/s of speed
        error (the torque-speed line at this duty, friction included), plus the friction
        torque when it helps (slowing down, or holding the wheel still in the dead-band)."""
        stall = self._stall[i]  # type: ignore[index]
        error = self._omega[i] - omega
        torque = stall / self._omega0[i] * abs(error)
        if error * omega <= 0.0:
            torque += stall * self._deadband
        return torque
