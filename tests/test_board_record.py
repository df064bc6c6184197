"""The board record: a runtime that takes the board writes where it is (bus, address,
emulator) into its runtime directory; ``jetbot-rt stop`` (systemd's ExecStopPost) reads it,
as an untrusted file, when its config cannot be read."""

from __future__ import annotations

import json
import os
import random
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hostile_user import needs_root, unused_uid

from jetbot_rt.hal.ownership import BoardLock
from jetbot_rt.service.runtime_dir import MAX_RECORD_BYTES, RECORD_NAME, read_board_record
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator


@pytest.fixture
def run_dir(private_runtime_dir: Path) -> Path:
    return private_runtime_dir


def test_taking_the_board_records_it_and_the_record_outlives_the_owner(run_dir: Path,
                                                                       tmp_path: Path) -> None:
    chip = tmp_path / "chip.json"
    PCA9685Emulator(0x41, state_file=chip)
    lock = BoardLock.acquire(3, str(chip), 0x41)
    lock.release()
    path = run_dir / RECORD_NAME
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert json.loads(path.read_text()) == {"i2c_bus": 3, "address": 0x41,
                                            "emulator": str(chip), "pid": os.getpid()}
    record, why = read_board_record()
    assert why is None and record is not None
    assert (record.i2c_bus, record.address, record.emulator, record.path) == \
        (3, 0x41, str(chip), path)
    assert sorted(p.name for p in run_dir.iterdir()) == [RECORD_NAME]  # no temporary left


def test_a_lock_taken_without_an_address_records_nothing(run_dir: Path, tmp_path: Path) -> None:
    BoardLock.acquire(1, str(tmp_path / "chip.json")).release()
    assert not (run_dir / RECORD_NAME).exists()
    assert read_board_record() == (None, "no board record in the runtime directory")


def _valid(tmp: Path) -> dict:
    chip = tmp / "chip.json"
    PCA9685Emulator(0x60, state_file=chip)
    return {"i2c_bus": 1, "address": 0x60, "emulator": str(chip), "pid": 1}


def _write(run_dir: Path, content: object) -> None:
    data = content if isinstance(content, bytes) else json.dumps(content).encode()
    (run_dir / RECORD_NAME).write_bytes(data)


BAD = {
    "symlink": None,
    "fifo": None,
    "directory": None,
    "oversized": b" " * (MAX_RECORD_BYTES + 1),
    "not-json": b"{bus: 1",
    "not-utf8": b'{"i2c_bus": "\xff"}',
    "a-list": [1, 96],
    "no-address": {"i2c_bus": 1},
    "unknown-key": {"i2c_bus": 1, "address": 96, "command": "rm -rf /"},
    "bool-bus": {"i2c_bus": True, "address": 96},
    "bus-300": {"i2c_bus": 300, "address": 96},
    "address-0x80": {"i2c_bus": 1, "address": 0x80},
    "address-text": {"i2c_bus": 1, "address": "0x60"},
    "emulator-relative": {"i2c_bus": 1, "address": 96, "emulator": "chip.json"},
    "emulator-gone": {"i2c_bus": 1, "address": 96, "emulator": "/nonexistent/chip.json"},
    "emulator-empty": {"i2c_bus": 1, "address": 96, "emulator": ""},
    "emulator-nul": {"i2c_bus": 1, "address": 96, "emulator": "/tmp/a\u0000b"},
    "emulator-a-link": "link",
    "pid-text": {"i2c_bus": 1, "address": 96, "pid": "1"},
}


@pytest.mark.parametrize("kind", list(BAD))
def test_a_record_that_is_not_one_is_ignored_and_said_why(run_dir: Path, tmp_path: Path,
                                                          kind: str) -> None:
    path = run_dir / RECORD_NAME
    if kind == "symlink":
        elsewhere = tmp_path / "record.json"
        elsewhere.write_text(json.dumps(_valid(tmp_path)))
        path.symlink_to(elsewhere)
    elif kind == "fifo":
        os.mkfifo(path)  # a blocking open would hang the stop
    elif kind == "directory":
        path.mkdir()
    elif kind == "emulator-a-link":
        record = _valid(tmp_path)
        (tmp_path / "link").symlink_to(record["emulator"])
        _write(run_dir, dict(record, emulator=str(tmp_path / "link")))
    else:
        _write(run_dir, BAD[kind])
    t0 = time.monotonic()
    record, why = read_board_record()
    assert time.monotonic() - t0 < 5.0  # catches a hang only
    assert record is None
    assert why is not None and str(path) in why, why
    assert "\n" not in why


@needs_root
def test_a_record_of_another_user_is_ignored(run_dir: Path, tmp_path: Path) -> None:
    _write(run_dir, _valid(tmp_path))
    hostile = unused_uid()
    os.chown(run_dir / RECORD_NAME, hostile, hostile)
    record, why = read_board_record()
    assert record is None
    assert why == f"{run_dir / RECORD_NAME} (owned by uid {hostile})"


def test_fuzzed_records_never_raise_and_only_valid_ones_are_used(run_dir: Path,
                                                                 tmp_path: Path) -> None:
    """Seeded, bounded: mutated bytes of a valid record. Each read returns a record within
    [motors]' ranges or None with a reason; none raises."""
    rng = random.Random(25)
    base = json.dumps(_valid(tmp_path)).encode()
    deadline = time.monotonic() + 5.0
    used = 0
    for _ in range(400):
        if time.monotonic() > deadline:
            break
        data = bytearray(base)
        for _ in range(rng.randint(1, 4)):
            at = rng.randrange(len(data))
            choice = rng.random()
            if choice < 0.4:
                data[at] = rng.randrange(256)
            elif choice < 0.7:
                del data[at]
            else:
                data.insert(at, rng.choice(b'0123456789"{}[],:-.eE \x00\xff'))
        _write(run_dir, bytes(data))
        record, why = read_board_record()
        if record is None:
            assert why
        else:
            used += 1
            assert 0 <= record.i2c_bus <= 255 and 0x03 <= record.address <= 0x77
            assert record.emulator is None or Path(record.emulator).is_file()
    assert used < 400


# ---- jetbot-rt stop with a config it cannot read (the good record: tests/test_stop.py) ------


def stop(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "jetbot_rt.cli", "stop", *args],
                          capture_output=True, text=True, timeout=30)


def test_stop_with_an_unreadable_config_and_a_bad_record_says_both(run_dir: Path,
                                                                   tmp_path: Path) -> None:
    _write(run_dir, {"i2c_bus": 1, "address": 0x80})
    config = tmp_path / "robot.toml"
    config.write_text("[motors]\nlayout = 'nope'\n")
    result = stop(tmp_path, "--config", str(config), "--board-emulator",
                  str(tmp_path / "chip.json"))
    assert result.returncode == 2, result.stdout + result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert "[motors] layout must be one of" in line
    assert "using the default bus and address" in line and "address must be 0x03..0x77" in line
    assert "motor outputs off (I2C bus 1 address 0x60)" in result.stdout


def test_a_readable_config_wins_over_the_record(run_dir: Path, tmp_path: Path) -> None:
    _write(run_dir, {"i2c_bus": 9, "address": 0x41})
    chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    config = tmp_path / "robot.toml"
    config.write_text("[motors]\ni2c_bus = 1\n")
    result = stop(tmp_path, "--config", str(config), "--board-emulator",
                  str(tmp_path / "chip.json"))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "I2C bus 1 address 0x60" in result.stdout and chip.refresh().sleeping


# ---- the directories themselves (runtime_dir's /tmp and /run rules) ---------------------------


@needs_root
def test_the_tmp_fallback_held_by_another_user_gives_way_to_our_own_alternative(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Another user made ``/tmp/jetbot-rt-<uid>`` first: the runtime takes the first
    ``/tmp/jetbot-rt-<uid>.*`` that is its own (closed to others again), passing over one of
    that user's, instead of a new one per run. ``/tmp`` is this test's own directory."""
    from jetbot_rt.service import runtime_dir

    monkeypatch.setattr(runtime_dir, "TMP", tmp_path)
    hostile, me = unused_uid(), os.getuid()
    taken = tmp_path / f"jetbot-rt-{me}"
    theirs = tmp_path / f"jetbot-rt-{me}.a"
    for path in (taken, theirs):
        path.mkdir(0o700)
        os.chown(path, hostile, hostile)
    mine = tmp_path / f"jetbot-rt-{me}.b"
    mine.mkdir()
    os.chmod(mine, 0o755)
    assert runtime_dir.private_dir(taken) == mine
    assert stat.S_IMODE(mine.stat().st_mode) == 0o700
    assert sorted(p.name for p in tmp_path.iterdir()) == [taken.name, theirs.name, mine.name]


@needs_root
@pytest.mark.parametrize(("run_mode", "service_mode", "trusted"), [
    (0o755, 0o700, True), (0o777, 0o700, False), (0o755, 0o770, False)])
def test_root_trusts_the_service_directory_whoever_owns_it_only_under_a_run_of_roots_alone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, run_mode: int, service_mode: int,
        trusted: bool) -> None:
    """``/run/jetbot-rt`` made by systemd for the service's user is root's to use too, as
    long as only root can have put it there (``/run`` root's, closed to others) and it is
    closed to others itself. ``/run`` is this test's own directory."""
    from jetbot_rt.errors import UsageError
    from jetbot_rt.service import runtime_dir

    run = tmp_path / "run"
    run.mkdir()
    os.chmod(run, run_mode)
    service = run / "jetbot-rt"
    service.mkdir()
    os.chmod(service, service_mode)
    hostile = unused_uid()
    os.chown(service, hostile, hostile)
    monkeypatch.setattr(runtime_dir, "SERVICE_DIR", service)
    if trusted:
        assert runtime_dir.private_dir(service) == service
        assert stat.S_IMODE(service.stat().st_mode) == service_mode  # not root's to change
    else:
        with pytest.raises(UsageError, match="not this user's own"):
            runtime_dir.private_dir(service)


def test_stop_trusts_only_real_sockets_in_its_directory(run_dir: Path, tmp_path: Path) -> None:
    """A file or a link named like a control socket is passed over and named, a real
    socket beside them is found."""
    import socket

    from jetbot_rt.service.runtime_dir import search

    (run_dir / "control-1.sock").write_text("")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        listener.bind(str(tmp_path / "elsewhere.sock"))
        (run_dir / "control-2.sock").symlink_to(tmp_path / "elsewhere.sock")
        real = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            real.bind(str(run_dir / "control-3.sock"))
            found = search("control-*.sock", 4)
        finally:
            real.close()
    finally:
        listener.close()
    assert found.sockets == [run_dir / "control-3.sock"]
    assert sorted(found.ignored) == [f"{run_dir / 'control-1.sock'} (not a socket)",
                                     f"{run_dir / 'control-2.sock'} (a symbolic link)"]
