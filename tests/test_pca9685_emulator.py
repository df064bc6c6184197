"""The PCA9685 emulator itself: the register behaviour the motor tests rely on."""

from __future__ import annotations

import errno
import os
import signal
import stat
import subprocess
import sys
import time

import pytest
from smbus2 import i2c_msg

from jetbot_rt.hal.pca9685 import ALL_LED_OFF_H, ALL_LED_ON_L, LED0_ON_L, MODE1, PRE_SCALE
from jetbot_rt.testing import pca9685_emulator
from jetbot_rt.testing.pca9685_emulator import STATE, PCA9685Emulator

ADDR = 0x60


def write(chip: PCA9685Emulator, *payload: int) -> None:
    chip.i2c_rdwr(i2c_msg.write(ADDR, bytes(payload)))


def read(chip: PCA9685Emulator, register: int, length: int) -> bytes:
    out, into = i2c_msg.write(ADDR, bytes((register,))), i2c_msg.read(ADDR, length)
    chip.i2c_rdwr(out, into)
    return bytes(into)


def test_power_on_state_is_asleep_and_all_off() -> None:
    chip = PCA9685Emulator(ADDR)
    assert read(chip, MODE1, 1) == b"\x11"
    assert chip.sleeping
    assert chip.registers[PRE_SCALE] == 0x1E
    assert chip.all_off()
    assert all(chip.channel(i).full_off for i in range(16))


def test_prescale_is_writable_only_in_sleep() -> None:
    chip = PCA9685Emulator(ADDR)
    write(chip, MODE1, 0x00)  # wake
    write(chip, PRE_SCALE, 5)
    assert chip.registers[PRE_SCALE] == 0x1E
    write(chip, MODE1, 0x10)  # sleep
    write(chip, PRE_SCALE, 5)
    assert chip.registers[PRE_SCALE] == 5
    assert chip.frequency == pytest.approx(25e6 / 4096 / 6)


def test_auto_increment_spreads_a_block_write_over_registers() -> None:
    chip = PCA9685Emulator(ADDR)
    write(chip, MODE1, 0x20)  # awake, AI
    write(chip, LED0_ON_L + 4, 0x00, 0x00, 0x00, 0x08)  # channel 1: off at 0x800
    assert chip.channel(1).duty == 0.5
    assert read(chip, LED0_ON_L + 4, 4) == b"\x00\x00\x00\x08"


def test_without_auto_increment_every_byte_lands_on_the_same_register() -> None:
    chip = PCA9685Emulator(ADDR)
    write(chip, MODE1, 0x00)  # awake, AI off
    write(chip, LED0_ON_L + 2, 0x11, 0x22, 0x33)
    assert chip.registers[LED0_ON_L + 2] == 0x33
    assert chip.registers[LED0_ON_L + 3] == 0x10  # untouched: still full-off


def test_all_led_registers_load_every_channel_and_read_back_zero() -> None:
    chip = PCA9685Emulator(ADDR)
    write(chip, MODE1, 0x20)
    write(chip, ALL_LED_ON_L, 0x00, 0x00, 0x00, 0x04)  # every channel 25 %
    assert chip.duties() == [0.25] * 16
    assert read(chip, ALL_LED_ON_L, 4) == b"\x00\x00\x00\x00"
    write(chip, ALL_LED_OFF_H, 0x10)
    assert chip.all_off()


def test_full_off_wins_over_full_on() -> None:
    chip = PCA9685Emulator(ADDR)
    write(chip, MODE1, 0x20)
    write(chip, LED0_ON_L, 0x00, 0x10, 0x00, 0x00)
    assert chip.channel(0).duty == 1.0
    write(chip, LED0_ON_L, 0x00, 0x10, 0x00, 0x10)
    assert chip.channel(0).full_on and chip.channel(0).full_off
    assert chip.channel(0).duty == 0.0


def test_asleep_the_outputs_hold_what_they_were_whatever_is_written() -> None:
    """Datasheet, MODE1 note 4: asleep, the outputs cannot be turned on, off or dimmed."""
    chip = PCA9685Emulator(ADDR)
    write(chip, MODE1, 0x20)
    write(chip, LED0_ON_L, 0x00, 0x10, 0x00, 0x00)  # channel 0 full on
    write(chip, MODE1, 0x30)
    assert chip.registers[MODE1] & 0x80  # RESTART: PWM was running when put to sleep
    assert chip.channel(0).duty == 1.0  # put to sleep while on: it stays on
    write(chip, 0xFD, 0x10)  # ALL_LED_OFF_H full off: the registers change, not the outputs
    assert chip.channel(0).full_off and chip.channel(0).duty == 1.0
    write(chip, MODE1, 0x20)  # awake: the registers drive again
    assert chip.all_off()


def test_off_then_asleep_no_led_write_turns_an_output_on() -> None:
    chip = PCA9685Emulator(ADDR)
    write(chip, MODE1, 0x20)
    write(chip, LED0_ON_L, 0x00, 0x00, 0x00, 0x08)  # channel 0 at 50 %
    write(chip, 0xFD, 0x10)
    write(chip, MODE1, 0x30)
    for payload in ((0x00, 0x10, 0x00, 0x00), (0x00, 0x00, 0x9A, 0x01)):
        write(chip, LED0_ON_L + 4, *payload)  # a runtime's next tick, on channel 1
        assert chip.all_off(), chip.duties()
    assert chip.channel(1).on_count == 0 and chip.channel(1).off_count == 0x19A


def test_injected_faults_and_absent_chip_raise_oserror() -> None:
    chip = PCA9685Emulator(ADDR)
    chip.update(fail_next=2)
    for _ in range(2):
        with pytest.raises(OSError):
            write(chip, MODE1, 0x20)
    write(chip, MODE1, 0x20)
    assert chip.registers[MODE1] == 0x20
    chip.update(absent=True)
    with pytest.raises(OSError):
        chip.write_quick(ADDR)
    with pytest.raises(OSError):
        PCA9685Emulator(ADDR).write_quick(0x40)  # nobody at that address


def test_two_instances_share_one_chip_through_the_state_file(tmp_path) -> None:
    state = tmp_path / "chip.json"
    writer = PCA9685Emulator(ADDR, state_file=state)
    reader = PCA9685Emulator(ADDR, state_file=state)
    write(writer, MODE1, 0x20)
    write(writer, LED0_ON_L + 8, 0x00, 0x00, 0x00, 0x02)
    assert reader.refresh().channel(2).duty == 0.125
    reader.update(fail_next=1)
    with pytest.raises(OSError):
        write(writer, MODE1, 0x20)


WRITER = """
import sys
from smbus2 import i2c_msg
from jetbot_rt.testing import pca9685_emulator
from jetbot_rt.testing.pca9685_emulator import STATE, PCA9685Emulator
chip = PCA9685Emulator(0x60, state_file=sys.argv[1])
chip.i2c_rdwr(i2c_msg.write(0x60, bytes((0x00, 0x20))))
print("ready", flush=True)
n = 0
while True:
    n = (n + 1) % 4000 + 16
    chip.i2c_rdwr(i2c_msg.write(0x60, bytes((0x06, 0, 0, n & 0xFF, n >> 8))))
"""


def test_state_file_survives_sigkill_of_a_writer(tmp_path) -> None:
    state = tmp_path / "chip.json"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(state)], stdout=subprocess.PIPE)
    try:
        assert proc.stdout is not None and proc.stdout.readline() == b"ready\n"
        time.sleep(0.3)  # many transactions in flight
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert state.stat().st_size == STATE.size
    chip = PCA9685Emulator(ADDR, state_file=state)  # whole, and the kernel released the lock
    write(chip, LED0_ON_L, 0x00, 0x00, 0x00, 0x10)
    assert chip.refresh().channel(0).full_off
    assert chip.transactions > 10


# ---- the state file: updated in place, never rewritten ------------------------------------


def test_a_transaction_updates_the_state_file_in_place(tmp_path) -> None:
    """No new file, no rename per write (those stalled ticks for 75-150 ms): the same inode,
    owner and mode after a thousand transactions, and nothing else in the directory but the
    owner lock's file."""
    state = tmp_path / "chip.json"
    chip = PCA9685Emulator(ADDR, state_file=state)
    os.chmod(state, 0o640)
    before = state.stat()
    write(chip, MODE1, 0x20)
    for n in range(1000):
        write(chip, LED0_ON_L, 0x00, 0x00, n & 0xFF, (n >> 8) & 0x0F)
    after = state.stat()
    assert (after.st_ino, after.st_uid, after.st_gid, stat.S_IMODE(after.st_mode)) == \
        (before.st_ino, before.st_uid, before.st_gid, 0o640)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["chip.json"]
    assert PCA9685Emulator(state_file=state).transactions == 1001


@pytest.mark.parametrize("kind", ["symlink", "fifo", "directory", "short", "json", "version"])
def test_a_state_file_that_is_not_one_is_refused(tmp_path, kind: str) -> None:
    state = tmp_path / "chip.json"
    real = tmp_path / "real.json"
    if kind == "symlink":
        PCA9685Emulator(ADDR, state_file=real)
        state.symlink_to(real)
    elif kind == "fifo":
        os.mkfifo(state)
    elif kind == "directory":
        state.mkdir()
    elif kind == "short":
        state.write_bytes(b"PCA9685E")
    elif kind == "json":  # the older JSON format, still read
        state.write_text('{"address": 96, "registers": []}')
    else:
        PCA9685Emulator(ADDR, state_file=state)
        with open(state, "r+b") as out:
            out.seek(8)
            out.write(b"\x07")
    with pytest.raises(OSError) as refused:
        PCA9685Emulator(ADDR, state_file=state)
    assert refused.value.errno in (errno.ELOOP, errno.EINVAL, errno.EISDIR), refused.value
    if kind == "symlink":
        assert PCA9685Emulator(state_file=real).sleeping  # what the link named is untouched


def test_a_lock_held_by_a_stopped_process_fails_the_transaction_not_the_caller(
        tmp_path, monkeypatch) -> None:
    """A writer stopped mid-transaction (SIGSTOP) keeps the lock: a transaction gives up
    after ``LOCK_WAIT_S`` with the error a bus that does not answer gives, then works again
    once the lock is free."""
    import fcntl

    monkeypatch.setattr(pca9685_emulator, "LOCK_WAIT_S", 0.2)
    state = tmp_path / "chip.json"
    chip = PCA9685Emulator(ADDR, state_file=state)
    holder = os.open(state, os.O_RDONLY)
    try:
        fcntl.flock(holder, fcntl.LOCK_EX)
        with pytest.raises(OSError) as stalled:
            write(chip, MODE1, 0x20)
        assert stalled.value.errno == errno.ETIMEDOUT
    finally:
        os.close(holder)
    write(chip, MODE1, 0x20)
    assert chip.refresh().registers[MODE1] == 0x20


def test_a_closed_emulator_opens_its_file_again(tmp_path) -> None:
    chip = PCA9685Emulator(ADDR, state_file=tmp_path / "chip.json")
    chip.close()
    write(chip, MODE1, 0x20)
    chip.close()
    chip.close()
    assert chip.refresh().registers[MODE1] == 0x20
