"""The smbus2-backed bus: busio.I2C's interface, retries, faults, opening the emulator."""

from __future__ import annotations

import pytest

from jetbot_rt.config.sections import MotorsConfig
from jetbot_rt.errors import Fault, UsageError
from jetbot_rt.hal.i2c import I2CBus, I2CFault, open_smbus
from jetbot_rt.hal.pca9685 import LED0_ON_L, MODE1
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

ADDR = 0x60


@pytest.fixture
def chip() -> PCA9685Emulator:
    return PCA9685Emulator(ADDR)


def test_transfers_honour_start_and_end(chip) -> None:
    bus = I2CBus(chip, 1)
    bus.writeto(ADDR, bytearray(b"\xff\x00\x20\xff"), start=1, end=3)  # MODE1 <- 0x20
    assert chip.registers[MODE1] == 0x20
    bus.writeto(ADDR, bytes((LED0_ON_L, 1, 2, 3, 4)))
    into = bytearray(6)
    bus.writeto_then_readfrom(ADDR, bytes((0xAA, LED0_ON_L)), into, out_start=1, in_start=1,
                              in_end=5)
    assert into == bytearray(b"\x00\x01\x02\x03\x04\x00")
    bus.writeto(ADDR, bytes((LED0_ON_L + 2,)))
    bus.readfrom_into(ADDR, into)
    assert into[:2] == b"\x03\x04"


def test_lock_is_exclusive(chip) -> None:
    bus = I2CBus(chip, 1)
    assert bus.try_lock()
    assert not bus.try_lock()
    bus.unlock()
    assert bus.try_lock()


def test_transient_errors_are_retried(chip) -> None:
    bus = I2CBus(chip, 1, retries=3)
    chip.update(fail_next=3)
    bus.writeto(ADDR, bytes((MODE1, 0x20)))
    assert chip.registers[MODE1] == 0x20
    assert chip.transactions == 4


def test_a_persistent_error_is_a_fault_naming_bus_and_address(chip) -> None:
    bus = I2CBus(chip, 7, retries=2)
    chip.update(fail_next=3)
    with pytest.raises(I2CFault, match=r"I2C bus 7 address 0x60: .*after 3 attempts") as info:
        bus.writeto(ADDR, bytes((MODE1, 0x20)))
    assert isinstance(info.value, Fault)
    assert chip.registers[MODE1] == 0x11  # nothing got through


def test_zero_length_write_probes_the_address(chip) -> None:
    bus = I2CBus(chip, 1, retries=0)
    bus.writeto(ADDR, b"")
    with pytest.raises(I2CFault, match="0x41"):
        bus.writeto(0x41, b"")
    assert I2CBus(chip, 1).scan() == [ADDR]


def test_adafruit_pca9685_runs_on_this_bus(chip) -> None:
    from adafruit_pca9685 import PCA9685

    pca = PCA9685(I2CBus(chip, 1), address=ADDR)
    pca.frequency = 1000
    pca.channels[5].duty_cycle = 0x8000
    assert chip.channel(5).duty == 0.5
    assert chip.frequency == pytest.approx(1000, rel=0.05)
    assert pca.channels[5].duty_cycle == 0x8000


def test_the_config_names_the_emulator(tmp_path) -> None:
    state = str(tmp_path / "chip.json")
    bus = I2CBus.for_motors(MotorsConfig(address=0x40, emulator=state))
    bus.writeto(0x40, bytes((MODE1, 0x20)))
    assert PCA9685Emulator(state_file=state).registers[MODE1] == 0x20


def test_the_environment_chooses_no_emulator(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("JETBOT_RT_I2C_EMULATOR", str(tmp_path / "chip.json"))
    with pytest.raises(UsageError, match="/dev/i2c-250"):
        open_smbus(250)
    assert not (tmp_path / "chip.json").exists()


def test_an_emulator_file_that_cannot_be_made_is_a_usage_error(tmp_path) -> None:
    with pytest.raises(UsageError, match=r"emulator's state file .*No such file"):
        open_smbus(1, emulator=str(tmp_path / "missing" / "chip.json"))


def test_missing_device_node_is_a_usage_error() -> None:
    with pytest.raises(UsageError, match="/dev/i2c-250"):
        open_smbus(250)


def test_missing_device_node_names_the_os_error_in_words() -> None:
    with pytest.raises(UsageError) as info:
        open_smbus(250)
    assert str(info.value) == ("cannot open /dev/i2c-250: No such file or directory (is the bus "
                               "enabled and is this user in the i2c group?)")


def test_defaults_three_retries_and_the_emulator_at_0x60(tmp_path) -> None:
    chip = PCA9685Emulator(0x60)
    chip.fail_next = 4
    with pytest.raises(I2CFault, match=r"\(after 4 attempts, \[motors\] i2c_retries = 3\)"):
        I2CBus(chip, 1).writeto(0x60, bytes((MODE1, 0x20)))
    chip.fail_next = 3
    I2CBus(chip, 1).writeto(0x60, bytes((MODE1, 0x20)))
    assert open_smbus(1, emulator=str(tmp_path / "chip.json")).address == 0x60


def test_a_combined_transfer_returns_what_its_read_got(chip) -> None:
    bus = I2CBus(chip, 1)
    # two writes, then MODE1 read back, all in one transaction
    got = bus.transfer(0x60, [bytes((MODE1, 0x31)), bytes((MODE1,))], read=1)
    assert got == bytes((0x31,))
    assert bus.transfer(0x60, [bytes((MODE1, 0x20))]) == b""
    assert chip.registers[MODE1] == 0x20


def test_retries_are_counted_from_zero_and_open_defaults_to_three(tmp_path) -> None:
    chip = PCA9685Emulator(0x60)
    bus = I2CBus(chip, 1)
    assert bus.retried == 0
    chip.fail_next = 2
    bus.writeto(0x60, bytes((MODE1, 0x20)))
    assert bus.retried == 2
    shared = PCA9685Emulator(0x60, state_file=tmp_path / "chip.json")
    shared.update(fail_next=3)
    with I2CBus.open(1, emulator=str(tmp_path / "chip.json")) as opened:
        opened.writeto(0x60, bytes((MODE1, 0x20)))
        assert opened.retried == 3


def test_write_then_read_sends_the_whole_write(chip) -> None:
    bus = I2CBus(chip, 1)
    got = bytearray(1)
    # MODE1 <- 0x31 (auto-increment on), then the pointer is at MODE2: read it
    bus.writeto_then_readfrom(0x60, bytes((MODE1, 0x31)), got)
    assert chip.registers[MODE1] == 0x31
    assert got[0] == chip.registers[MODE1 + 1]


@pytest.mark.parametrize("address", [0x03, 0x60, 0x77])
def test_scan_covers_every_7_bit_address_from_0x03_to_0x77(address) -> None:
    assert I2CBus(PCA9685Emulator(address), 1).scan() == [address]


@pytest.mark.parametrize("reserved", [0x00, 0x02, 0x78, 0x7F])
def test_scan_never_probes_a_reserved_address(reserved) -> None:
    assert I2CBus(PCA9685Emulator(reserved), 1).scan() == []


def test_each_retry_waits_a_millisecond_longer_than_the_one_before(chip) -> None:
    waits: list[float] = []
    bus = I2CBus(chip, 1, retries=3, sleep=waits.append)
    chip.update(fail_next=3)
    bus.writeto(ADDR, bytes((MODE1, 0x20)))
    assert waits == pytest.approx([0.001, 0.002, 0.003])
    waits.clear()
    chip.update(fail_next=4)
    with pytest.raises(I2CFault):
        bus.writeto(ADDR, bytes((MODE1, 0x20)))
    assert waits == pytest.approx([0.001, 0.002, 0.003]), "no wait after the last attempt"
