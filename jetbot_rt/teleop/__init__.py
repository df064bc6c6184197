"""Hand inputs for ``jetbot-rt drive`` (docs/DRIVE.md): a keyboard in a terminal, a Linux
joystick, the simulator's scripted stand-in for a person; and the ``Arbiter`` that decides,
each tick, whether the policy or the person drives.

Every input only *proposes* a command (``HandCommand``: ``[left, right]`` in the policy's
action space, -1..1, and whether it takes over). The command goes through the same action
pipeline (``max_speed``, trim, sign), the same guarded drive and the same latch as a policy's:
a hand command can never exceed what a policy may do, and a stop always wins over it.

A command older than the deadman time (``DEADMAN_S``, at most ``MAX_DEADMAN_S``) is no command:
the wheels get zero (the person drives alone) or go back to the policy (a take-over ended).
An input that is lost (terminal closed, device unplugged) trips the latch: motors zero, the
``input_lost`` event, exit 3.
"""

from __future__ import annotations

from jetbot_rt.teleop.hand import (
    DEADMAN_S,
    MAX_DEADMAN_S,
    Arbiter,
    HandCommand,
    HandInput,
)

__all__ = ["DEADMAN_S", "MAX_DEADMAN_S", "Arbiter", "HandCommand", "HandInput"]
