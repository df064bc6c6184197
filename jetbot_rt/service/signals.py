"""Which signals end a run in the safe stop, and how a command installs its handlers.

signal(7), every signal whose default action ends or stops the process, decided one by one:

- **Caught, safe stop, orderly end** (exit 0, ``<NAME> received``): SIGINT, SIGTERM, SIGHUP,
  SIGQUIT, SIGUSR1, SIGALRM, SIGVTALRM, SIGPROF, SIGIO, SIGPWR, SIGSTKFLT, SIGXCPU
  (the CPU-time soft limit: the hard limit's SIGKILL follows), SIGTRAP and SIGSYS sent by
  ``kill``, and every real-time signal SIGRTMIN..SIGRTMAX.
- **Caught, every thread's stack, safe stop as a fault** (exit 3): SIGUSR2, the unit's
  ``WatchdogSignal=`` (``WATCHDOG``). The stacks are read in Python, in the main thread, while
  it holds the GIL: no other thread can run Python meanwhile, so every frame read is one that
  stands still. (faulthandler's dump from a C signal handler reads the other threads' frames
  while they run: after systemd's SIGCONT to a stopped service it crashed with SIGSEGV in 3 of
  6 trials.) A process so wedged that this handler never runs (the GIL held for ever by a
  native call) gets the unit's ``FinalKillSignal=SIGABRT`` ``TimeoutAbortSec=`` later: then
  no thread can run Python, and faulthandler's dump of every thread is safe.
- **Caught, safe stop, then suspended** (SIGTSTP: Ctrl-Z; SIGTTIN, SIGTTOU: a background job
  touching the terminal): the motors go to zero first, then the process stops itself with
  SIGSTOP as the shell expects. On SIGCONT (``fg``) **the run ends** (exit 0): a robot that
  starts driving again by itself when someone types ``fg`` is a surprise; start it again.
- **Left to Python**: SIGPIPE and SIGXFSZ, which CPython ignores so that the write fails
  with an ``OSError`` instead (telemetry counts it as lost records and keeps driving).
- **Not caught, by decision**: SIGABRT (the unit's ``FinalKillSignal``; a native ``abort()``)
  means Python may no longer run, so a Python handler would keep the process alive;
  faulthandler dumps every thread's stack and the process dies, then ``ExecStopPost`` turns
  the board off. SIGSEGV, SIGBUS, SIGFPE, SIGILL are memory or CPU faults: the process state
  cannot be trusted; faulthandler dumps the stacks, the process dies, ``ExecStopPost`` stops
  the board. (After the watchdog signal's own dump, a later SIGABRT prints only the stack of
  the thread it lands on: the other threads may be running again.)
- **Cannot be caught**: SIGKILL (``ExecStopPost``), SIGSTOP (the motors keep their duty while
  the process is stopped; systemd's watchdog ends a stopped service, a manual run has nothing).
"""

from __future__ import annotations

import _thread
import contextlib
import faulthandler
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, TextIO

_TERMINATING_NAMES = (
    "SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM", "SIGVTALRM",
    "SIGPROF", "SIGIO", "SIGPWR", "SIGSTKFLT", "SIGXCPU", "SIGTRAP", "SIGSYS",
)
_SUSPENDING_NAMES = ("SIGTSTP", "SIGTTIN", "SIGTTOU")


def _present(names: tuple[str, ...]) -> list[int]:
    found = []
    for name in names:
        number = getattr(signal, name, None)
        if number is not None and int(number) not in found:  # SIGIO == SIGPOLL
            found.append(int(number))
    return found


def _realtime() -> list[int]:
    low, high = getattr(signal, "SIGRTMIN", None), getattr(signal, "SIGRTMAX", None)
    return list(range(int(low), int(high) + 1)) if low and high else []


TERMINATING: list[int] = _present(_TERMINATING_NAMES) + _realtime()
"""Signals whose default action ends the process and that end a run in the safe stop."""
SUSPENDING: list[int] = _present(_SUSPENDING_NAMES)
"""Signals whose default action stops the process: safe stop, then suspend; the run ends."""
HANDLED: list[int] = TERMINATING + SUSPENDING
WATCHDOG: int = int(signal.SIGUSR2)
"""The unit's ``WatchdogSignal=``: every thread's stack, then the safe stop as a fault."""
FAULTING: list[int] = [WATCHDOG]
"""Handled signals whose stop is a fault (exit 3), not an orderly end."""
MAX_FRAMES = 100
"""Frames printed per thread, innermost first (faulthandler prints as many)."""


def name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        low = getattr(signal, "SIGRTMIN", 0)
        return f"SIGRTMIN+{signum - low}" if low and signum >= low else f"signal {signum}"


def install(handler: Callable[[int, Any], None]) -> None:
    """``handler`` for every signal in ``HANDLED`` (main thread only); once
    ``enable_stack_dumps`` ran, the watchdog signal's prints every thread's stack first."""
    for signum in HANDLED:
        chosen = handler
        if signum == WATCHDOG and _stack_file is not None and handler is not raise_interrupted:
            chosen = _stacks_first(handler)
        with contextlib.suppress(OSError, ValueError, RuntimeError):  # not settable here
            signal.signal(signum, chosen)
    if handler is raise_interrupted and not isinstance(sys.unraisablehook, _SendAgain):
        sys.unraisablehook = _SendAgain(sys.unraisablehook)


_stack_file: TextIO | None = None


def enable_stack_dumps(file: TextIO | None = None) -> None:
    """For a command that drives: SIGABRT, SIGSEGV, SIGBUS, SIGFPE and SIGILL print every
    thread's stack (faulthandler, from C: Python may be wedged) before the process dies, and
    the handler ``install`` gives ``WATCHDOG`` prints them from Python first. ``file``: the
    interpreter's own stderr by default (the journal under systemd), else ``sys.stderr``.
    Without any (a run started with stderr closed) the run drives without stack dumps: they
    would have nowhere to go (``console`` keeps fd 2 on /dev/null, never another file)."""
    global _stack_file
    for candidate in (file, sys.__stderr__, sys.stderr):
        if candidate is not None:
            _stack_file = candidate
            break
    # ValueError/OSError: a stream without a descriptor; RuntimeError: none at all
    with contextlib.suppress(ValueError, OSError, AttributeError, RuntimeError):
        faulthandler.enable(file=_stack_file, all_threads=True)


def _stacks_first(handler: Callable[[int, Any], None]) -> Callable[[int, Any], None]:
    def stacks_then_stop(signum: int, frame: Any) -> None:
        # Past this point the threads run again (the stop below, a SIGCONT): a later SIGABRT
        # (the unit's FinalKillSignal) must read no frame but its own thread's.
        with contextlib.suppress(ValueError, OSError, AttributeError, RuntimeError):
            faulthandler.enable(file=_stack_file, all_threads=False)
        text = (f"jetbot-rt: {name(signum)} (systemd's WatchdogSignal: no WATCHDOG=1 within "
                f"WatchdogSec): the stack of every thread, most recent call first\n"
                + thread_stacks(frame))
        handler(signum, frame)  # the stop is not held up by the printing
        with contextlib.suppress(Exception):  # a closed or reentered stream: stacks lost
            print(text, end="", file=sys.stderr, flush=True)

    return stacks_then_stop


def thread_stacks(interrupted: Any = None) -> str:
    """Every Python thread's stack, innermost frame first, in faulthandler's layout plus the
    thread's name. Call it holding the GIL (any Python code does): no other thread runs
    Python meanwhile, so no frame changes while it is read. ``interrupted``: the frame a
    signal handler interrupted, shown for the calling thread instead of the handler's own.

    Takes no lock (``threading.enumerate()`` would take one that the interrupted code may
    hold) and does no I/O."""
    names = {ident: thread.name for ident, thread in dict(threading._active).items()}  # type: ignore[attr-defined]
    me = threading.get_ident()
    lines = []
    for ident, frame in sys._current_frames().items():
        if ident == me and interrupted is not None:
            frame = interrupted
        current = " (current)" if ident == me else ""
        lines.append(f"Thread {names.get(ident, '?')} 0x{ident:016x}{current}:")
        for _ in range(MAX_FRAMES):
            if frame is None:
                break
            code = frame.f_code
            lines.append(f'  File "{code.co_filename}", line {frame.f_lineno} in {code.co_name}')
            frame = frame.f_back
        if frame is not None:
            lines.append("  ...")
        lines.append("")
    return "\n".join(lines)


def suspend_self() -> None:
    """Stop this process as the default SIGTSTP would (SIGSTOP cannot be caught)."""
    import os

    os.kill(os.getpid(), signal.SIGSTOP)


class Interrupted(BaseException):
    """Raised by ``raise_interrupted``: a signal arrived while nothing drives (start-up, a
    command between two steps); the command ends in order."""

    def __init__(self, signum: int) -> None:
        super().__init__(name(signum))
        self.signum = signum


_held: list[int] | None = None
_in_hook = False
_raised: list[int] = []
"""Signals whose ``Interrupted`` ``raise_interrupted`` raised (see ``raised_first``)."""


def raise_interrupted(signum: int, _frame: Any) -> None:
    """The handler of commands that do not drive yet: raise ``Interrupted`` in the main
    thread, unless inside ``deferred()``, which raises it when it ends."""
    if _in_hook:  # raised inside _SendAgain, it would be lost: later, once more
        _send_again_later(signum)
        return
    if _held is not None:
        _held.append(signum)
        return
    _raised.append(signum)
    raise Interrupted(signum)


def raised_first() -> int | None:
    """The first signal whose ``Interrupted`` was raised, if any: C code it was raised in can
    replace it with an error of its own (numpy's extension init: "ImportError: PyCapsule_Import
    could not import module datetime"), which then reaches the command's end in its place."""
    return _raised[0] if _raised else None


def raise_if_swallowed() -> None:
    """Raise ``Interrupted`` again if one was raised in this process and the command went on:
    code it was raised in swallowed it (OpenCV's loader has a bare ``except:``; C code can turn
    it into an ``ImportError`` that an optional import catches). For the points before a
    command moves a motor."""
    signum = raised_first()
    if signum is not None:
        raise Interrupted(signum)


class _SendAgain:
    """``sys.unraisablehook`` that does not let Python swallow an ``Interrupted``.

    Python runs a signal handler between two bytecodes of the main thread, and that can be
    inside a weakref callback, a ``__del__`` or the garbage collector (the import system's
    module-lock callbacks, during start-up's imports): an exception raised there cannot
    propagate; Python prints "Exception ignored in ..." and carries on. Seen: a SIGQUIT 0.3 s
    into ``jetbot-rt run`` lost this way, and the run drove for its whole duration. Instead,
    the signal is sent again, once, from another thread a moment later: its handler runs
    again where the main thread is then (raising there, or, once ``run`` has installed its
    own handlers, tripping the safe stop). Sent from here, the handler would run at once,
    inside this hook."""

    def __init__(self, previous: Callable[[Any], object]) -> None:
        self.previous = previous

    def __call__(self, unraisable: Any) -> None:
        global _in_hook
        if not isinstance(unraisable.exc_value, Interrupted):
            self.previous(unraisable)
            return
        _in_hook = True
        try:
            _send_again_later(unraisable.exc_value.signum)
        finally:
            _in_hook = False


def _send_again_later(signum: int) -> None:
    with contextlib.suppress(RuntimeError):  # the interpreter is shutting down
        _thread.start_new_thread(_send_again, (signum,))


def _send_again(signum: int) -> None:
    time.sleep(0.01)  # the hook has returned
    os.kill(os.getpid(), signum)


@contextlib.contextmanager
def deferred(raise_after: bool = True) -> Iterator[None]:
    """A stop in progress is never cut short by ``raise_interrupted``: a signal that arrives
    inside the block is raised when it ends (``raise_after``), or absorbed. (Blocking with
    ``pthread_sigmask`` would not do: another thread would take the signal and Python would
    still run the handler.)"""
    global _held
    outer = _held
    if outer is None:
        _held = []
    try:
        yield
    finally:
        if outer is None:
            pending, _held = _held, None
            if pending and raise_after:
                raise Interrupted(pending[0])
