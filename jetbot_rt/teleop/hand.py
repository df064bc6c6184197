"""The hand command, the input base class with its deadman, and the ``Arbiter``."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

DEADMAN_S = 0.25
"""Seconds a hand command stays valid after it arrived (the default of ``--deadman``)."""
MAX_DEADMAN_S = 0.3
"""The longest deadman ``--deadman`` accepts: a released key or button stops the wheels
within this plus one control period."""

POLICY = "policy"
HUMAN = "human"


@dataclass(frozen=True)
class HandCommand:
    """What a person asks for: ``mu`` = ``[left, right]`` in -1..1 (the policy's action space);
    ``takeover``: while a policy drives, this command replaces the policy's."""

    mu: tuple[float, float]
    takeover: bool = True


ZERO = HandCommand((0.0, 0.0))


class HandInput:
    """An input. A reader thread (or the control thread, for ``scripted``) calls ``propose``;
    the control thread calls ``command(now)`` each tick and gets the newest command unless it
    is older than ``deadman_s``. ``lost(reason)`` says the input is gone for good: it calls
    ``on_lost`` once (the drive trips the latch there)."""

    name = "input"

    def __init__(self, deadman_s: float = DEADMAN_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.deadman_s = deadman_s
        self.clock = clock
        self.on_lost: Callable[[str], None] = lambda reason: None
        self.on_quit: Callable[[str], None] = lambda reason: None
        self.lost_reason: str | None = None
        self._lock = threading.Lock()
        self._latest: HandCommand | None = None
        self._at = -float("inf")

    # ---- the reader's side --------------------------------------------------------------

    def propose(self, command: HandCommand, at: float | None = None) -> None:
        with self._lock:
            self._latest = command
            self._at = self.clock() if at is None else at

    def release(self) -> None:
        """The person let go (a button released): no command from now on."""
        with self._lock:
            self._latest = None

    def lost(self, reason: str) -> None:
        with self._lock:
            if self.lost_reason is not None:
                return
            self.lost_reason = reason
            self._latest = None
        self.on_lost(reason)

    # ---- the control thread's side ------------------------------------------------------

    def command(self, now: float) -> HandCommand | None:
        """The command in force at ``now``: the newest, unless older than the deadman."""
        with self._lock:
            if self._latest is None or now - self._at > self.deadman_s:
                return None
            return self._latest

    def start(self) -> None:
        """Begin reading (a thread); inputs without one need nothing."""

    def close(self) -> None:
        """Stop reading and give back what was opened (the terminal's mode)."""

    def describe(self) -> dict[str, Any]:
        return {"input": self.name, "deadman_s": self.deadman_s}


def _pair(values: Any) -> list[float]:
    return [round(float(values[0]), 4), round(float(values[1]), 4)]


class Arbiter:
    """The loop's policy for ``jetbot-rt drive``: each tick it runs the policy (if any) and
    asks the hand input, then returns the action to apply. Without a policy the person drives
    every tick (no command in force: zero). With one the policy drives unless a hand command
    that takes over is in force: human-gated DAgger (HG-DAgger), the takeover ticks are the
    labels. ``marks`` says what this tick did (``driver``, ``human``, ``policy_mu``), for
    the records; ``switches`` counts the takeovers."""

    def __init__(self, policy: Any, hand: HandInput,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.policy = policy
        self.hand = hand
        self.clock = clock
        self.driver = HUMAN if policy is None else POLICY
        self.marks: dict[str, Any] = {"driver": self.driver}
        self.switched: str | None = None
        """``takeover`` or ``handback`` when this tick changed the driver, else None."""
        self.takeovers = 0
        self.human_ticks = 0
        self.ticks = 0

    def infer(self, image: np.ndarray) -> np.ndarray:
        policy_mu = None if self.policy is None else self.policy.infer(image)
        hand = self.hand.command(self.clock())
        if policy_mu is None:
            driver = HUMAN
            mu = hand.mu if hand is not None else ZERO.mu
        elif hand is not None and hand.takeover:
            driver, mu = HUMAN, hand.mu
        else:
            driver, mu = POLICY, policy_mu
        self.switched = None
        if driver != self.driver and policy_mu is not None:
            self.switched = "takeover" if driver == HUMAN else "handback"
            self.takeovers += driver == HUMAN
        self.driver = driver
        self.ticks += 1
        self.human_ticks += driver == HUMAN
        self.marks = {"driver": driver, "human": _pair(hand.mu) if hand is not None else None}
        if policy_mu is not None:
            self.marks["policy_mu"] = _pair(policy_mu)
        return np.asarray(mu, dtype=np.float32)
