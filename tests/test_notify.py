"""The notify protocol against a real AF_UNIX datagram socket, as systemd would bind it."""

from __future__ import annotations

import os
import socket
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from jetbot_rt.service.systemd_notify import Notifier


class Listener:
    """A bound datagram socket standing in for systemd's notify socket."""

    def __init__(self, name: str, address: str | bytes) -> None:
        self.name = name  # what goes into NOTIFY_SOCKET
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)
        self.sock.setblocking(False)

    def messages(self) -> list[dict[str, str]]:
        """Every datagram queued so far (delivery on a local socket is synchronous)."""
        received = []
        while True:
            try:
                data = self.sock.recv(4096)
            except BlockingIOError:
                return received
            received.append(dict(line.split("=", 1) for line in data.decode().split("\n")))


@pytest.fixture(params=["path", "abstract"])
def listener(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Listener]:
    if request.param == "path":
        path = str(tmp_path / "notify.sock")
        listen = Listener(path, path)
    else:
        name = f"jetbot-rt-test-{uuid.uuid4().hex}"
        listen = Listener("@" + name, b"\0" + name.encode())
    yield listen
    listen.sock.close()


def notifier_for(
    listener: Listener,
    monkeypatch: pytest.MonkeyPatch,
    watchdog_usec: int | None = 300_000,
    watchdog_pid: str | None = None,
) -> Notifier:
    monkeypatch.setenv("NOTIFY_SOCKET", listener.name)
    if watchdog_usec is None:
        monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    else:
        monkeypatch.setenv("WATCHDOG_USEC", str(watchdog_usec))
    if watchdog_pid is None:
        monkeypatch.delenv("WATCHDOG_PID", raising=False)
    else:
        monkeypatch.setenv("WATCHDOG_PID", watchdog_pid)
    return Notifier.from_env()


def test_ready_status_and_stopping_arrive(listener: Listener, monkeypatch: pytest.MonkeyPatch):
    notifier = notifier_for(listener, monkeypatch)
    notifier.ready("running at 30 Hz")
    notifier.stopping("safe stop: SIGTERM")
    assert listener.messages() == [
        {"READY": "1", "STATUS": "running at 30 Hz"},
        {"STOPPING": "1", "STATUS": "safe stop: SIGTERM"},
    ]


def test_watchdog_every_third_of_watchdog_usec_after_ready_only(
    listener: Listener, monkeypatch: pytest.MonkeyPatch
):
    notifier = notifier_for(listener, monkeypatch, watchdog_usec=300_000)
    assert notifier.watchdog_enabled
    assert notifier.watchdog_interval == pytest.approx(0.1)
    statuses = iter(range(1000))

    def status() -> str:
        return f"tick {next(statuses)}"

    notifier.tick(0.0, status)
    assert listener.messages() == [], "nothing before READY=1"
    notifier.ready("ready")
    listener.messages()

    pings, status_times = [], []
    for step in range(301):  # 3 s of ticks at 100 Hz, times made up: no sleeping
        now = 10.0 + step * 0.01
        notifier.tick(now, status)
        for message in listener.messages():
            if "WATCHDOG" in message:
                assert message["WATCHDOG"] == "1"
                pings.append(now)
            if "STATUS" in message:
                status_times.append(now)
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    assert pings[0] == 10.0, "the first completed tick after READY pings at once"
    assert max(gaps) <= 0.15, "at least twice per WATCHDOG_USEC (0.3 s)"
    assert min(gaps) >= 0.099, "not on every tick"
    assert len(status_times) == 4  # t = 10, 11, 12, 13: at most once per second
    assert all(b - a >= 0.999 for a, b in zip(status_times, status_times[1:]))


def test_no_watchdog_when_watchdog_pid_is_another_process(
    listener: Listener, monkeypatch: pytest.MonkeyPatch
):
    notifier = notifier_for(listener, monkeypatch, watchdog_pid=str(os.getpid() + 1))
    assert not notifier.watchdog_enabled
    assert notifier.watchdog_interval is None
    notifier.ready("ready")
    for step in range(50):
        notifier.tick(step * 0.1, lambda: "running")
    messages = listener.messages()
    assert not any("WATCHDOG" in m for m in messages)
    assert any("STATUS" in m for m in messages[1:]), "status still goes out"


def test_watchdog_when_watchdog_pid_is_this_process(
    listener: Listener, monkeypatch: pytest.MonkeyPatch
):
    notifier = notifier_for(listener, monkeypatch, watchdog_pid=str(os.getpid()))
    assert notifier.watchdog_enabled
    notifier.ready("ready")
    notifier.tick(1.0, lambda: "running")
    assert listener.messages()[-1]["WATCHDOG"] == "1"


def test_no_watchdog_without_watchdog_usec(listener: Listener, monkeypatch: pytest.MonkeyPatch):
    notifier = notifier_for(listener, monkeypatch, watchdog_usec=None)
    assert not notifier.watchdog_enabled
    notifier.ready("ready")
    notifier.tick(1.0, lambda: "running")
    assert not any("WATCHDOG" in m for m in listener.messages())


def test_nothing_after_stopping(listener: Listener, monkeypatch: pytest.MonkeyPatch):
    notifier = notifier_for(listener, monkeypatch)
    notifier.ready("ready")
    notifier.stopping("stopping")
    listener.messages()
    notifier.tick(100.0, lambda: "still ticking")
    assert listener.messages() == []


def test_status_stays_one_line(listener: Listener, monkeypatch: pytest.MonkeyPatch):
    notifier = notifier_for(listener, monkeypatch)
    notifier.ready("camera ok\nREADY=0")
    assert listener.messages() == [{"READY": "1", "STATUS": "camera ok READY=0"}]


def test_without_notify_socket_nothing_happens(monkeypatch: pytest.MonkeyPatch, capsys):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.setenv("WATCHDOG_USEC", "300000")
    notifier = Notifier.from_env()
    assert not notifier.enabled
    assert not notifier.watchdog_enabled
    notifier.ready("ready")
    notifier.tick(1.0, lambda: pytest.fail("status() must not be called"))
    notifier.stopping("stopping")
    assert capsys.readouterr().err == ""


def test_send_errors_are_reported_once_and_never_raised(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
):
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "nobody-listens.sock"))
    monkeypatch.setenv("WATCHDOG_USEC", "300000")
    notifier = Notifier.from_env()
    notifier.ready("ready")
    for step in range(10):
        notifier.tick(step * 1.0, lambda: "running")
    notifier.stopping("stopping")
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "cannot notify systemd" in err and "nobody-listens.sock" in err


class TestPingsAtIrregularTickTimes:
    """Real ticks never land exactly on the next ping's due time: with jittered tick times,
    a ping goes out with the first tick at or after each due time, and never earlier."""

    def test_ping_and_status_schedule(self, listener: Listener,
                                      monkeypatch: pytest.MonkeyPatch) -> None:
        notifier = notifier_for(listener, monkeypatch, watchdog_usec=300_000)
        notifier.ready("ready")
        listener.messages()
        pings, statuses, due, status_due = [], [], None, None
        times = [20.0 + step * 0.0137 + (step % 3) * 0.0011 for step in range(250)]
        for now in times:
            notifier.tick(now, lambda: "running")
            for message in listener.messages():
                if "WATCHDOG" in message:
                    pings.append(now)
                if "STATUS" in message:
                    statuses.append(now)
            # each tick at or after a due time must have pinged
            if due is not None and now >= due:
                assert pings[-1] == now, (now, due)
            if pings and pings[-1] == now:
                due = now + 0.1
            if status_due is not None and now >= status_due:
                assert statuses[-1] == now
            if statuses and statuses[-1] == now:
                status_due = now + 1.0
        assert pings[0] == times[0] and statuses[0] == times[0]
        assert all(b - a >= 0.1 for a, b in zip(pings, pings[1:]))
        assert all(b - a < 0.1 + 0.0137 + 0.0023 for a, b in zip(pings, pings[1:]))
        assert len(statuses) == 4  # 0, ~1, ~2, ~3 s into 3.4 s of ticks


class TestAFullNotifySocketNeverBlocks:
    """A service manager that stops reading (its queue full) must not stall the control loop:
    sends give up at once, the failure is said once, and nothing is raised."""

    def test_sends_to_a_full_queue_return(self, tmp_path: Path, capfd) -> None:
        path = str(tmp_path / "notify.sock")
        listener = Listener(path, path)  # bound, never read from
        try:
            notifier = Notifier(path, watchdog_usec=3)
            notifier.ready("ready")
            finished = threading.Event()

            def flood() -> None:
                for step in range(20_000):  # far more datagrams than the queue holds
                    notifier.tick(float(step), lambda: "running " + "x" * 200)
                finished.set()

            thread = threading.Thread(target=flood, daemon=True)
            thread.start()
            assert finished.wait(60), "a send blocked on the full queue"
            err = capfd.readouterr().err
            assert err.count("cannot notify systemd") == 1, err
        finally:
            listener.sock.close()


class TestUnparsableEnvironment:
    """systemd's variables as text a bug or a hand-written unit could give: never a crash,
    and no watchdog unless it is clearly ours."""

    @pytest.mark.parametrize(("usec", "pid", "enabled"), [
        ("abc", None, False), ("0", None, False), ("-5", None, False), ("1", None, True),
        ("300000", "x", False), ("300000", "-3", False), ("300000", "0", False),
    ])
    def test_values(self, listener: Listener, monkeypatch: pytest.MonkeyPatch,
                    usec: str, pid: str | None, enabled: bool) -> None:
        monkeypatch.setenv("NOTIFY_SOCKET", listener.name)
        monkeypatch.setenv("WATCHDOG_USEC", usec)
        if pid is None:
            monkeypatch.delenv("WATCHDOG_PID", raising=False)
        else:
            monkeypatch.setenv("WATCHDOG_PID", pid)
        assert Notifier.from_env().watchdog_enabled is enabled


class TestClose:
    def test_close_releases_the_socket_and_is_safe_before_any_send(self, listener: Listener,
                                                                   monkeypatch) -> None:
        Notifier(listener.name, 300_000).close()  # nothing sent yet: nothing to close
        before = len(os.listdir("/proc/self/fd"))
        notifier = notifier_for(listener, monkeypatch)
        notifier.ready("ready")
        assert len(os.listdir("/proc/self/fd")) == before + 1
        notifier.close()
        notifier.close()
        assert len(os.listdir("/proc/self/fd")) == before


def test_a_closed_notifier_opens_a_new_socket_for_a_later_message(listener: Listener,
                                                                  monkeypatch) -> None:
    notifier = notifier_for(listener, monkeypatch)
    notifier.ready("ready")
    notifier.close()
    notifier.stopping("stopping")
    assert [m.get("STOPPING") for m in listener.messages()] == [None, "1"]
