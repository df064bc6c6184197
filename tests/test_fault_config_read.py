"""Fault matrix, configs that cannot be read (class 1): every command reads its
config in bounded time and memory; each failure is one line on stderr, exit 2, no traceback,
no hang. ``jetbot-rt stop`` (systemd's ExecStopPost) writes the hardware stop all the same,
on the default bus and address, before it reports.

The board is the register-level PCA9685 emulator, driven at duty 0.10 / 0.05 (what a runtime
leaves behind) before each ``stop``.
"""

from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from fault_helpers import record_figures
from runner import JETBOT_RT, on_emulator, wait_for

from jetbot_rt.hal.i2c import I2CBus
from jetbot_rt.hal.motors import WaveshareDrive
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

TIMEOUT_S = 20.0
"""A hang fails the case: a stop or a refusal takes an interpreter start, well under this."""
BOARD_OFF_S = 10.0
"""Bound asserted on: ``jetbot-rt stop`` started -> every output of the board off."""


def latin1_comment(tmp: Path) -> Path:
    path = tmp / "latin1.toml"
    path.write_bytes("# vitesse réglée\n[motors]\ni2c_bus = 1\n".encode("latin-1"))
    return path


def invalid_start_byte(tmp: Path) -> Path:
    path = tmp / "ff.toml"
    path.write_bytes(b"\xff\xfe[loop]\nrate_hz = 30\n")
    return path


def nested_50000(tmp: Path) -> Path:
    path = tmp / "nested.toml"
    path.write_text("x = " + "[" * 50_000 + "]" * 50_000 + "\n")
    return path


def oversized(tmp: Path) -> Path:
    path = tmp / "big.toml"
    path.write_text(("# " + "x" * 1022 + "\n") * 400)  # 400 KiB of comments
    return path


def fifo_no_writer(tmp: Path) -> Path:
    path = tmp / "fifo.toml"
    os.mkfifo(path)
    return path


def dev_zero(_tmp: Path) -> Path:
    return Path("/dev/zero")


def a_directory(tmp: Path) -> Path:
    path = tmp / "conf.d"
    path.mkdir()
    return path


BAD: dict[str, tuple[Callable[[Path], Path], str]] = {
    "non-utf8-comment": (latin1_comment, "is not UTF-8: byte 0xe9 at line 1"),
    "non-utf8-first-byte": (invalid_start_byte, "is not UTF-8: byte 0xff at line 1"),
    "nested-50000": (nested_50000, "nested too deeply"),
    "oversized": (oversized, "larger than 256 KiB"),
    "fifo": (fifo_no_writer, "not a regular file"),
    "dev-zero": (dev_zero, "not a regular file"),
    "directory": (a_directory, "a directory"),
}


def driven_board(tmp: Path) -> PCA9685Emulator:
    chip = PCA9685Emulator(0x60, state_file=tmp / "chip.json")
    WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0).write(0.10, 0.05)
    assert not chip.refresh().all_off()
    return chip


def env_for(tmp: Path, **extra: str) -> dict[str, str]:
    return dict(os.environ, **{"JETBOT_RT_RUNTIME_DIR": str(tmp / "run"), **extra})


def jetbot_rt(tmp: Path, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([JETBOT_RT, *on_emulator(list(args), tmp / "chip.json")],
                          capture_output=True, text=True,
                          timeout=TIMEOUT_S, env=env or env_for(tmp), cwd=tmp)


def assert_one_line(stderr: str, expected: str) -> str:
    assert "Traceback" not in stderr, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert expected in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("kind", list(BAD))
def test_stop_writes_the_hardware_stop_whatever_the_config(tmp_path: Path, kind: str) -> None:
    make, expected = BAD[kind]
    chip = driven_board(tmp_path)
    config = make(tmp_path)
    t0 = time.monotonic()
    proc = subprocess.Popen([JETBOT_RT, "stop", "--config", str(config), "--board-emulator",
                             str(tmp_path / "chip.json")], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=env_for(tmp_path), cwd=tmp_path)
    try:
        t_off = wait_for(lambda: chip.refresh().all_off(), BOARD_OFF_S, 0.02)
        assert t_off is not None
        out, err = proc.communicate(timeout=TIMEOUT_S)
        t_done = time.monotonic()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 2, out + err
    line = assert_one_line(err, expected)
    assert "using the default bus and address" in line
    assert "motor outputs off (I2C bus 1 address 0x60)" in out
    assert chip.refresh().all_off(), chip.duties()
    record_figures(f"stop-config-{kind}", exit_code=proc.returncode,
                   stop_to_board_off_s=round(t_off - t0, 4), stop_cmd_s=round(t_done - t0, 4))


@pytest.mark.parametrize(("command", "kind"), [
    ("run", "non-utf8-comment"), ("run", "fifo"), ("run", "nested-50000"),
    ("check", "dev-zero"), ("check", "oversized"),
    ("install-service", "fifo"), ("install-service", "non-utf8-first-byte"),
])
def test_every_command_refuses_an_unreadable_config_in_one_line(tmp_path: Path, command: str,
                                                                kind: str) -> None:
    make, expected = BAD[kind]
    chip = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    before = chip.refresh().transactions
    config = make(tmp_path)
    if command == "install-service":
        root = tmp_path / "root"
        staged = root / "etc" / "jetbot-rt" / "config.toml"
        staged.parent.mkdir(parents=True)
        if kind == "fifo":
            os.mkfifo(staged)
        else:
            staged.write_bytes(config.read_bytes())
        args = ["install-service", "--root", str(root), "--user", "root"]
    elif command == "run":
        args = ["run", "--backend", "real", "--config", str(config), "--duration", "1"]
    else:
        args = ["check", "--config", str(config)]
    result = jetbot_rt(tmp_path, *args)
    assert result.returncode == 2, result.stdout + result.stderr
    assert_one_line(result.stderr, expected)
    assert chip.refresh().transactions == before, "the board was touched"
    if command == "install-service":
        assert not (root / "etc" / "systemd").exists(), "wrote a unit next to a broken config"


def test_a_byte_order_mark_is_accepted(tmp_path: Path) -> None:
    chip = driven_board(tmp_path)
    config = tmp_path / "bom.toml"
    config.write_bytes(b"\xef\xbb\xbf[motors]\naddress = 0x60\ni2c_retries = 1\n")
    result = jetbot_rt(tmp_path, "stop", "--config", str(config))
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""
    assert chip.refresh().all_off()
