"""The control socket and ``jetbot-rt stop`` (as a subprocess, on the emulated board)."""

from __future__ import annotations

import os
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from jetbot_rt.errors import UsageError
from jetbot_rt.hal.i2c import I2CBus
from jetbot_rt.hal.motors import BoardAsleep, WaveshareDrive
from jetbot_rt.service.stop_socket import ControlServer, default_socket_path, request_stop
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

# ---- control channel ---------------------------------------------------------------------


@pytest.fixture
def sock_path(tmp_path) -> Path:
    return tmp_path / "run" / "control.sock"


def test_stop_request_reaches_the_runtime_with_the_callers_pid(sock_path) -> None:
    reasons: list[str] = []
    server = ControlServer(reasons.append, sock_path)
    server.start()
    try:
        assert stat.S_IMODE(sock_path.stat().st_mode) == 0o600
        assert stat.S_IMODE(sock_path.parent.stat().st_mode) == 0o700
        assert request_stop(sock_path)
        assert reasons == [f"jetbot-rt stop from pid {os.getpid()}"]
    finally:
        server.close()
    assert not sock_path.exists()
    assert not request_stop(sock_path)


def test_no_runtime_means_no_acknowledgement(sock_path) -> None:
    t0 = time.monotonic()
    assert not request_stop(sock_path)
    assert time.monotonic() - t0 < 2.0


def test_a_stale_socket_file_is_replaced(sock_path) -> None:
    sock_path.parent.mkdir(mode=0o700)
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(str(sock_path))
    dead.close()  # the file stays, nobody listens: a runtime that died
    reasons: list[str] = []
    server = ControlServer(reasons.append, sock_path)
    server.start()
    try:
        assert request_stop(sock_path)
        assert len(reasons) == 1
    finally:
        server.close()


def test_a_stale_socket_alone_is_answered_without_sitting_out_the_timeout(sock_path) -> None:
    """Nothing to wait for once the only socket refused: the asking ends (it waited out its
    whole timeout on an empty selector, so `jetbot-rt stop` after a crash answered 1 s late).
    Asked with an hour's timeout, it must end long before."""
    sock_path.parent.mkdir(mode=0o700)
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(str(sock_path))
    dead.close()
    replies = []
    asking = threading.Thread(target=lambda: replies.append(request_stop(sock_path, 3600.0)),
                              daemon=True)
    asking.start()
    asking.join(60.0)
    assert not asking.is_alive(), "request_stop waited out its timeout on a stale socket"
    assert not replies[0] and not replies[0].acknowledged and not replies[0].unreachable


def test_a_live_socket_is_not_taken_over(sock_path) -> None:
    first = ControlServer(lambda _r: None, sock_path)
    first.start()
    try:
        with pytest.raises(UsageError, match="in use by another process"):
            ControlServer(lambda _r: None, sock_path).start()
        assert request_stop(sock_path)  # the first still serves
    finally:
        first.close()


def test_runtimes_side_by_side_are_all_asked_to_stop(tmp_path, monkeypatch) -> None:
    """One socket per runtime (``control-<pid>.sock``): two simulations do not refuse each
    other, and ``stop`` asks both. A dead runtime's socket is cleared by the next start."""
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path / "run"))
    reasons: list[str] = []
    other = ControlServer(reasons.append, tmp_path / "run" / "control-other.sock")
    mine = ControlServer(reasons.append)
    assert mine.path == tmp_path / "run" / f"control-{os.getpid()}.sock"
    dead = tmp_path / "run" / f"control-{2**22 + 1}.sock"  # above pid_max's default: no pid
    try:
        other.start()
        left = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        left.bind(str(dead))
        left.close()  # the file stays: a runtime that was killed
        mine.start()  # clears the dead one's file
        assert not dead.exists()
        reply = request_stop()
        assert sorted(reply.acknowledged) == sorted([other.path, mine.path])
        assert len(reasons) == 2 and not reply.unreachable
    finally:
        for server in (other, mine):
            server.close()


def test_default_socket_path_precedence(monkeypatch) -> None:
    for name in ("JETBOT_RT_RUNTIME_DIR", "RUNTIME_DIRECTORY", "XDG_RUNTIME_DIR"):
        monkeypatch.delenv(name, raising=False)
    mine = f"control-{os.getpid()}.sock"
    # root never falls back to /tmp, where another user can create the name first
    fallback = Path("/run/jetbot-rt") if os.getuid() == 0 else Path(f"/tmp/jetbot-rt-{os.getuid()}")
    assert default_socket_path() == fallback / mine
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/run/user/7")
    assert default_socket_path() == Path("/run/user/7/jetbot-rt") / mine
    monkeypatch.setenv("RUNTIME_DIRECTORY", "/run/jetbot-rt:/run/other")
    assert default_socket_path() == Path("/run/jetbot-rt") / mine
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", "/x")
    assert default_socket_path() == Path("/x") / mine


# ---- jetbot-rt stop ----------------------------------------------------------------------


def stop_command(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run"))
    return subprocess.run(
        [sys.executable, "-m", "jetbot_rt.cli", "stop", "--board-emulator",
         str(tmp_path / "chip.json"), *args],
        capture_output=True, text=True, timeout=30, env=env,
    )


def test_stop_turns_a_driven_board_off_without_a_runtime(tmp_path) -> None:
    chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0).write(0.6, -0.6)
    assert not chip.refresh().all_off()
    t0 = time.monotonic()
    result = stop_command(tmp_path)
    elapsed = time.monotonic() - t0
    assert result.returncode == 0, result.stderr
    assert "motor outputs off" in result.stdout
    assert chip.refresh().all_off()
    assert elapsed < 10.0  # generous: a whole interpreter start on a loaded 2-core machine


def test_stop_asks_a_running_runtime_first(tmp_path) -> None:
    tripped = threading.Event()
    server = ControlServer(lambda _reason: tripped.set(), tmp_path / "run" / "control.sock")
    server.start()
    try:
        result = stop_command(tmp_path)
    finally:
        server.close()
    assert result.returncode == 0, result.stderr
    assert tripped.is_set()
    assert "latched its safe stop" in result.stdout


def test_stop_fails_clearly_when_the_board_does_not_answer(tmp_path) -> None:
    PCA9685Emulator(0x60, state_file=tmp_path / "chip.json").update(absent=True)
    config = tmp_path / "robot.toml"
    config.write_text("[motors]\ni2c_retries = 1\n")
    result = stop_command(tmp_path, "--config", str(config))
    assert result.returncode == 1
    assert "motors NOT confirmed off (I2C bus 1 address 0x60)" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_stop_loads_no_camera_policy_or_torch(tmp_path) -> None:
    code = (
        "import sys\n"
        "from jetbot_rt.cli import main\n"
        "assert main(['stop', '--board-emulator', sys.argv[1]]) == 0\n"
        "heavy = {'torch', 'onnxruntime', 'cv2', 'pybullet', 'jetbot_rt.hal.gst_camera',\n"
        "         'jetbot_rt.runtime.policy', 'adafruit_motorkit'}\n"
        "print(sorted(heavy & set(sys.modules)))\n"
    )
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run"))
    result = subprocess.run([sys.executable, "-c", code, str(tmp_path / "chip.json")],
                            capture_output=True, text=True, timeout=30, env=env)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_stop_with_a_broken_config_still_turns_the_board_off(tmp_path) -> None:
    chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0).write(0.6, 0.6)
    config = tmp_path / "robot.toml"
    config.write_text("[motors]\nlayout = 'edited-while-running'\n")
    result = stop_command(tmp_path, "--config", str(config))
    assert result.returncode == 2
    assert "[motors] layout must be one of" in result.stderr
    assert "using the default bus and address" in result.stderr
    assert chip.refresh().all_off()


def test_stop_reports_a_runtime_it_could_not_reach(tmp_path) -> None:
    # A socket that accepts but never answers: a runtime stuck, or one we may not talk to.
    sock_path = tmp_path / "run" / "control.sock"
    sock_path.parent.mkdir(mode=0o700)
    silent = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    silent.bind(str(sock_path))
    silent.listen(1)
    chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0).write(0.6, 0.6)
    try:
        result = stop_command(tmp_path)
    finally:
        silent.close()
    # The board is off and asleep and nobody owns the bus: confirmed; the socket is a note.
    assert result.returncode == 0, result.stderr
    assert "note: could not ask 1 runtime socket(s) to stop" in result.stderr
    assert "no answer within 1 s" in result.stderr
    assert chip.refresh().all_off() and chip.sleeping


def silent_sockets(directory: Path, count: int) -> list[socket.socket]:
    """Sockets that accept (the kernel queues the connection) and never answer."""
    directory.mkdir(mode=0o700, exist_ok=True)
    listeners = []
    for n in range(count):
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(str(directory / f"control-{n}.sock"))
        listener.listen(4)
        listeners.append(listener)
    return listeners


def test_sockets_that_do_not_answer_are_one_line_that_counts_them(tmp_path) -> None:
    chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    listeners = silent_sockets(tmp_path / "run", 6)
    try:
        result = stop_command(tmp_path)
    finally:
        for listener in listeners:
            listener.close()
    assert result.returncode == 0, result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("jetbot-rt stop: note: could not ask 6 runtime socket(s) to stop: ")
    assert line.count("no answer within 1 s") == 4 and line.endswith("; and 2 more"), line
    assert chip.refresh().all_off() and chip.sleeping


@pytest.mark.parametrize("count", range(10))
def test_a_line_names_four_and_counts_the_rest(count: int) -> None:
    from jetbot_rt.commands.stop import MAX_NAMED, _listed

    items = [f"p{n}" for n in range(count)]
    more = f"; and {count - MAX_NAMED} more" if count > MAX_NAMED else ""
    assert _listed(items) == "; ".join(items[:MAX_NAMED]) + more


def test_a_board_that_cannot_be_read_back_is_not_confirmed(tmp_path) -> None:
    """The stop went out, then the board's file became unreadable (held owner: ``stop``
    waits for it, meanwhile the file is swapped for a directory): exit 1, one line, not a
    traceback or a usage error."""
    import fcntl

    chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0).write(0.6, 0.6)
    owner = os.open(tmp_path / "chip.json.owner", os.O_RDONLY | os.O_CREAT, 0o666)
    fcntl.flock(owner, fcntl.LOCK_EX)
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run"))
    stop = subprocess.Popen([sys.executable, "-m", "jetbot_rt.cli", "stop", "--board-emulator",
                             str(tmp_path / "chip.json")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 20
        while not chip.refresh().sleeping and time.monotonic() < deadline:
            time.sleep(0.005)
        (tmp_path / "chip.json").rename(tmp_path / "was-chip.json")
        (tmp_path / "chip.json").mkdir()
        out, err = stop.communicate(timeout=30)
    finally:
        os.close(owner)
        if stop.poll() is None:
            stop.kill()
            stop.communicate()
    assert stop.returncode == 1, out + err
    (line,) = err.strip().splitlines()
    assert "motors NOT confirmed off" in line and "cannot read the board back" in line, line


@pytest.mark.parametrize("kind", ["symlink", "writable-by-others"])
def test_a_runtime_directory_it_does_not_trust_is_named_and_not_asked(tmp_path,
                                                                     kind: str) -> None:
    reasons: list[str] = []
    server = ControlServer(reasons.append, tmp_path / "real" / "control.sock")
    server.start()
    if kind == "symlink":
        (tmp_path / "run").symlink_to(tmp_path / "real")
        why = f"{tmp_path / 'run'} (a symbolic link)"
    else:
        (tmp_path / "real").rename(tmp_path / "run")
        os.chmod(tmp_path / "run", 0o777)
        why = f"{tmp_path / 'run'} (writable by others (mode 0777))"
    try:
        result = stop_command(tmp_path)
    finally:
        server.close()
    assert result.returncode == 0, result.stderr
    assert reasons == [] and "latched" not in result.stdout
    (line,) = result.stderr.strip().splitlines()
    assert line == f"jetbot-rt stop: ignored: {why}"


def test_a_first_stop_the_bus_refused_is_written_again_after_the_asking(tmp_path) -> None:
    chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0).write(0.6, 0.6)
    chip.update(fail_next=1)  # a burst as long as the first write's attempts
    config = tmp_path / "robot.toml"
    config.write_text("[motors]\ni2c_retries = 0\n")
    result = stop_command(tmp_path, "--config", str(config))
    assert result.returncode == 0, result.stdout + result.stderr
    assert chip.refresh().all_off() and chip.sleeping


def test_stop_with_an_unreadable_config_stops_the_board_the_runtime_recorded(
        tmp_path, monkeypatch) -> None:
    """No ``--board-emulator``: bus, address and board come from the record the runtime wrote
    when it took the board (the defaults, bus 1 at 0x60, have no board here)."""
    from jetbot_rt.hal.ownership import BoardLock

    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path / "run"))
    chip_file = tmp_path / "chip.json"
    chip = PCA9685Emulator(0x41, state_file=chip_file)
    BoardLock.acquire(4, str(chip_file), 0x41).release()
    WaveshareDrive(I2CBus(chip, 4), 0x41, 1600.0).write(0.6, -0.6)
    config = tmp_path / "robot.toml"
    config.write_bytes(b"\xff not a config")
    result = subprocess.run([sys.executable, "-m", "jetbot_rt.cli", "stop", "--config",
                             str(config)], capture_output=True, text=True, timeout=30)
    assert result.returncode == 2, result.stdout + result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert "is not UTF-8" in line
    assert line.endswith(f"; using the board the runtime recorded in {tmp_path}/run/board.json")
    assert "motor outputs off (I2C bus 4 address 0x41)" in result.stdout
    assert f"EMULATOR in {chip_file}" in result.stdout
    assert chip.refresh().all_off() and chip.sleeping


class TestStopNeverReportsAnOffItCouldNotWrite:
    """Whatever keeps the hardware stop from reaching the board -- no device node, a board that
    does not answer, a bus that fails every transfer, a bad config on top -- ``stop`` exits
    non-zero, says NOT confirmed in one line and never prints "motor outputs off"."""

    @staticmethod
    def stop_without_emulator(tmp_path: Path, config: str) -> subprocess.CompletedProcess[str]:
        path = tmp_path / "robot.toml"
        path.write_text(config)
        env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run"))
        return subprocess.run(
            [sys.executable, "-m", "jetbot_rt.cli", "stop", "--config", str(path)],
            capture_output=True, text=True, timeout=30, env=env,
        )

    @pytest.mark.parametrize("bus", [7, 255])
    def test_a_bus_that_cannot_be_opened(self, tmp_path: Path, bus: int) -> None:
        assert not Path(f"/dev/i2c-{bus}").exists()
        result = self.stop_without_emulator(tmp_path, f"[motors]\ni2c_bus = {bus}\n")
        assert result.returncode == 1, result.stdout + result.stderr
        assert "motor outputs off" not in result.stdout
        [line] = result.stderr.strip().splitlines()
        assert line.startswith(f"jetbot-rt stop: motors NOT confirmed off (I2C bus {bus} ")
        assert f"/dev/i2c-{bus}" in line

    def test_a_bad_config_and_no_bus_is_still_not_confirmed(self, tmp_path: Path) -> None:
        assert not Path("/dev/i2c-1").exists()
        result = self.stop_without_emulator(tmp_path, "[motors]\nlayout = 'nope'\n")
        assert result.returncode == 1, result.stdout + result.stderr
        assert "motor outputs off" not in result.stdout
        assert "using the default bus and address" in result.stderr
        assert "motors NOT confirmed off (I2C bus 1 address 0x60)" in result.stderr
        assert "Traceback" not in result.stderr

    def test_the_old_environment_variable_chooses_no_emulator(self, tmp_path: Path,
                                                              monkeypatch) -> None:
        """A stray ``JETBOT_RT_I2C_EMULATOR`` in the environment chooses nothing: only the
        explicit flag swaps the board for the emulator, so the stop goes to the configured
        bus."""
        monkeypatch.setenv("JETBOT_RT_I2C_EMULATOR", str(tmp_path / "chip.json"))
        result = self.stop_without_emulator(tmp_path, "[motors]\ni2c_bus = 7\n")
        assert result.returncode == 1, result.stdout + result.stderr
        assert "/dev/i2c-7" in result.stderr and "EMULATOR" not in result.stdout
        assert not (tmp_path / "chip.json").exists()

    def test_a_bus_that_fails_every_transfer(self, tmp_path: Path) -> None:
        chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
        WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0).write(0.6, 0.6)
        chip.update(fail_next=100)
        config = tmp_path / "robot.toml"
        config.write_text("[motors]\ni2c_retries = 2\n")
        result = stop_command(tmp_path, "--config", str(config))
        assert result.returncode == 1, result.stdout + result.stderr
        assert "motor outputs off" not in result.stdout
        assert "motors NOT confirmed off" in result.stderr
        assert not chip.refresh().all_off()  # true: it could not be written


class TestARuntimesLastTickAfterTheStop:
    """``stop`` puts the chip to sleep before it asks anyone: a runtime's tick in flight while
    it is asked (its write lands after the stop) changes registers only, never an output, and
    finds the chip asleep (a fault for that runtime: it stops)."""

    def test_a_write_made_while_acknowledging_drives_nothing(self, tmp_path: Path) -> None:
        chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
        drive = WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0)
        drive.write(0.6, 0.6)
        seen: list[tuple[str, bool, bool]] = []

        def last_tick_then_latch(_reason: str) -> None:
            board = PCA9685Emulator(state_file=tmp_path / "chip.json")
            asleep_before = board.refresh().sleeping and board.all_off()
            try:
                drive.write(0.4, -0.4)  # the tick in flight lands after the stop
                outcome = "written"
            except BoardAsleep:
                outcome = "asleep"
            seen.append((outcome, asleep_before, board.refresh().all_off()))

        server = ControlServer(last_tick_then_latch, tmp_path / "run" / "control.sock")
        server.start()
        try:
            result = stop_command(tmp_path)
        finally:
            server.close()
        assert seen == [("asleep", True, True)], seen
        assert chip.refresh().all_off() and chip.sleeping, chip.duties()
        assert chip.channel(1).off_count == 0x666  # the late duty reached the registers only
        assert result.returncode == 0, result.stdout + result.stderr
        assert "motor outputs off" in result.stdout
