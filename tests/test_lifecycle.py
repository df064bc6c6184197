"""The run's lifecycle driver: phases entered in order, released in reverse, the latch looked
at between every two, and a start-up step in a worker that a stop request ends at once."""

from __future__ import annotations

import signal
import threading
import time

import pytest

from jetbot_rt.commands.lifecycle import Cancelled, Lifecycle, Phase
from jetbot_rt.runtime.safety import SafeStopLatch


class Recorded(Phase):
    """A phase that writes what happens to it in a shared list."""

    def __init__(self, name: str, log: list[str], fail_in: str = "",
                 on_enter: object = None) -> None:
        self.name = name  # only this test's log: the runtime's phases are named by class
        self.log = log
        self.fail_in = fail_in
        self.on_enter = on_enter

    def enter(self) -> None:
        self.log.append(f"enter {self.name}")
        if callable(self.on_enter):
            self.on_enter()
        if self.fail_in == "enter":
            raise RuntimeError(f"{self.name} failed halfway")

    def exit(self) -> None:
        self.log.append(f"exit {self.name}")
        if self.fail_in == "exit":
            raise OSError(f"{self.name} cannot close")


def test_phases_are_released_in_reverse_order_of_entry() -> None:
    log: list[str] = []
    life = Lifecycle(SafeStopLatch())
    life.run([Recorded(n, log) for n in ("a", "b", "c")])
    life.unwind()
    assert log == ["enter a", "enter b", "enter c", "exit c", "exit b", "exit a"]


def test_a_phase_that_fails_halfway_is_released_and_the_next_is_never_entered() -> None:
    log: list[str] = []
    life = Lifecycle(SafeStopLatch())
    with pytest.raises(RuntimeError, match="b failed halfway"):
        life.run([Recorded("a", log), Recorded("b", log, fail_in="enter"), Recorded("c", log)])
    life.unwind()
    assert log == ["enter a", "enter b", "exit b", "exit a"]


def test_a_stop_between_two_phases_cancels_the_start_before_the_next() -> None:
    log: list[str] = []
    latch = SafeStopLatch()
    life = Lifecycle(latch)
    stop = Recorded("a", log, on_enter=lambda: latch.trip("SIGTERM received", fault=False))
    with pytest.raises(Cancelled):
        life.run([stop, Recorded("b", log)])
    life.unwind()
    assert log == ["enter a", "exit a"]


def test_a_signal_whose_interrupt_was_swallowed_during_the_start_ends_it_before_the_next_phase(
        monkeypatch) -> None:
    from jetbot_rt.service import signals

    log: list[str] = []
    life = Lifecycle(SafeStopLatch())
    swallow = Recorded("a", log, on_enter=lambda: signals._raised.append(signal.SIGINT))
    monkeypatch.setattr(signals, "_raised", [])
    with pytest.raises(signals.Interrupted, match="SIGINT"):
        life.run([swallow, Recorded("b", log)])
    life.unwind()
    assert log == ["enter a", "exit a"]


def test_an_exit_that_fails_is_said_in_one_line_and_the_others_still_run(capsys) -> None:
    log: list[str] = []
    life = Lifecycle(SafeStopLatch())
    life.run([Recorded("a", log), Recorded("b", log, fail_in="exit"), Recorded("c", log)])
    life.unwind()
    life.unwind()  # each phase at most once
    assert log[3:] == ["exit c", "exit b", "exit a"]
    assert capsys.readouterr().err == "jetbot-rt: cleanup: b cannot close\n"


def test_a_stop_request_ends_a_step_stuck_in_a_worker_at_once() -> None:
    latch = SafeStopLatch()
    life = Lifecycle(latch)
    release = threading.Event()
    threading.Timer(0.1, latch.trip, args=("jetbot-rt stop",)).start()
    t0 = time.monotonic()
    with pytest.raises(Cancelled):
        life.in_worker("hang", lambda: release.wait(60), limit=60)
    assert time.monotonic() - t0 < 30, "bound only catches a hang"
    assert [t.name for t in life.stuck] == ["jetbot-rt-hang"]
    release.set()
    life.stuck[0].join(10)
    life.exit_if_stuck(3)  # nothing is stuck any more: it returns


def test_a_worker_step_returns_its_value_raises_its_error_or_times_out() -> None:
    life = Lifecycle(SafeStopLatch())
    assert life.in_worker("ok", lambda: 42, limit=30) == 42

    def broken() -> int:
        raise ValueError("bad model")

    with pytest.raises(ValueError, match="bad model"):
        life.in_worker("bad", broken, limit=30)
    release = threading.Event()
    with pytest.raises(TimeoutError):
        life.in_worker("slow", lambda: release.wait(60), limit=0.05)
    release.set()
