"""Test doubles shipped with the package, for this project's tests and an outside harness.

Nothing in the product imports from here unless a run names a double explicitly: the PCA9685
emulator stands in for the motor board only with ``--board-emulator STATE_FILE`` (or
``[motors] emulator``), and every command that uses it says so (docs/HARDWARE.md).
"""
