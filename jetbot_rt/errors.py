"""The two kinds of failure the command line distinguishes."""


class UsageError(Exception):
    """Bad input: flags, config, model file. One line to the user, exit code 2, motors untouched."""


class Fault(Exception):
    """Something went wrong while driving. Latches the safe stop; the run ends with exit code 3."""

    STOP_REQUEST_GRACE_S = 0.0
    """How long the loop waits for an orderly stop request before it calls this a fault: a
    fault that an orderly stop itself causes sets it (see ``hal.motors.BoardAsleep``)."""


EXIT_OK = 0
EXIT_USAGE = 2
EXIT_SAFE_STOP = 3


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (libraries often append pages of context)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
