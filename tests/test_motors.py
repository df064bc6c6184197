"""Both motor layouts on the emulated PCA9685: the chip's outputs after each command."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from jetbot_rt.config.sections import MotorsConfig
from jetbot_rt.errors import Fault, UsageError
from jetbot_rt.hal.i2c import I2CBus, I2CFault
from jetbot_rt.hal.motors import (
    MODE1_AI,
    MotorHatDrive,
    WaveshareDrive,
    hardware_stop,
    open_drive,
    prescale_for,
    read_mode1,
)
from jetbot_rt.hal.pca9685 import PRE_SCALE
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

ADDR = 0x60
STEP = 1 / 4096  # one PCA9685 count


def outputs(chip: PCA9685Emulator, channels: tuple[int, ...]) -> list[float]:
    return [chip.channel(c).duty for c in channels]


@pytest.fixture
def chip() -> PCA9685Emulator:
    return PCA9685Emulator(ADDR)


@pytest.fixture
def waveshare(chip) -> WaveshareDrive:
    return WaveshareDrive(I2CBus(chip, 1), ADDR, 1600.0)


def motorhat(chip: PCA9685Emulator, left: int = 1, right: int = 2) -> MotorHatDrive:
    return MotorHatDrive(I2CBus(chip, 1), ADDR, 1600.0, left, right)


# ---- waveshare: left (1, 0), right (2, 3) ------------------------------------------------


def test_waveshare_setup_wakes_the_chip_with_auto_increment_and_all_off(chip, waveshare) -> None:
    assert not chip.sleeping
    assert chip.registers[0x00] & 0x20
    assert chip.frequency == pytest.approx(1526, abs=1)  # 1600 Hz rounds to the chip's maximum
    assert chip.all_off()


def test_waveshare_forward_reverse_zero(chip, waveshare) -> None:
    waveshare.write(0.5, 0.25)
    assert outputs(chip, (1, 0, 2, 3)) == [0.5, 0.0, 0.25, 0.0]
    waveshare.write(-0.5, -0.25)
    assert outputs(chip, (1, 0, 2, 3)) == [0.0, 0.5, 0.0, 0.25]
    assert chip.channel(1).full_off and chip.channel(2).full_off
    waveshare.write(0.0, 0.0)
    assert chip.all_off()
    waveshare.write(1.0, -1.0)
    assert chip.channel(1).full_on and chip.channel(3).full_on
    assert outputs(chip, (1, 0, 2, 3)) == [1.0, 0.0, 0.0, 1.0]


def test_waveshare_tick_is_one_block_write(chip, waveshare) -> None:
    before = chip.transactions
    waveshare.write(0.3, -0.7)
    assert chip.transactions - before == 1
    assert outputs(chip, (1, 3)) == pytest.approx([0.3, 0.7], abs=STEP)
    assert chip.duties()[4:] == [0.0] * 12


def test_waveshare_refuses_non_finite_duties(chip, waveshare) -> None:
    waveshare.write(0.4, 0.4)
    with pytest.raises(Fault):
        waveshare.write(math.nan, 0.0)
    assert outputs(chip, (1, 2)) == pytest.approx([0.4, 0.4], abs=STEP)


def test_hardware_stop_is_one_two_byte_write_that_turns_everything_off(chip, waveshare) -> None:
    chip.registers[0x06 + 4 * 9 + 1] = 0x10  # some other channel full-on
    waveshare.write(0.8, -0.8)
    transactions, sent = chip.transactions, chip.bytes
    waveshare.stop()
    assert (chip.transactions - transactions, chip.bytes - sent) == (1, 2)
    assert chip.all_off()
    waveshare.write(0.2, 0.2)  # a later write drives again
    assert outputs(chip, (1, 2)) == pytest.approx([0.2, 0.2], abs=STEP)


def test_transient_i2c_errors_are_absorbed_persistent_ones_fault(chip, waveshare) -> None:
    chip.update(fail_next=2)
    waveshare.write(0.5, 0.5)
    assert outputs(chip, (1, 2)) == [0.5, 0.5]
    chip.update(fail_next=100)
    with pytest.raises(I2CFault, match="bus 1 address 0x60"):
        waveshare.write(-0.5, -0.5)
    assert outputs(chip, (1, 2)) == [0.5, 0.5]  # the chip holds the last good write
    chip.update(fail_next=0)
    waveshare.stop()
    assert chip.all_off()


# ---- adafruit_motorhat via MotorKit -----------------------------------------------------
# motor1: PWM 8, IN2 9, IN1 10 -> forward on 9; motor2: PWM 13, IN2 11, IN1 12 -> forward on 11


def test_motorhat_forward_reverse_zero(chip) -> None:
    drive = motorhat(chip)
    assert chip.channel(8).full_on and chip.channel(13).full_on  # TB6612 PWM inputs
    drive.write(0.5, 0.25)
    assert outputs(chip, (9, 10, 11, 12)) == pytest.approx([0.5, 0, 0.25, 0], abs=STEP)
    drive.write(-0.5, -0.25)
    assert outputs(chip, (9, 10, 11, 12)) == pytest.approx([0, 0.5, 0, 0.25], abs=STEP)
    drive.write(0.0, 0.0)
    assert outputs(chip, (9, 10, 11, 12)) == [0.0] * 4


def test_motorhat_motor_choice_and_stop_then_drive_again(chip) -> None:
    drive = motorhat(chip, left=3, right=4)  # motor3: 2 (PWM), 3, 4; motor4: 7 (PWM), 5, 6
    drive.write(0.5, -0.5)
    assert outputs(chip, (3, 4, 5, 6)) == pytest.approx([0.5, 0, 0, 0.5], abs=STEP)
    drive.stop()
    assert chip.all_off()
    drive.write(0.25, 0.25)  # the PWM inputs the hardware stop cleared come back
    assert chip.channel(2).full_on and chip.channel(7).full_on
    assert outputs(chip, (3, 5)) == pytest.approx([0.25, 0.25], abs=STEP)


def test_motorhat_same_motor_twice_is_a_usage_error(chip) -> None:
    with pytest.raises(UsageError, match="left_motor and right_motor"):
        motorhat(chip, left=2, right=2)


def test_hardware_stop_function_on_a_bare_bus(chip) -> None:
    motorhat(chip).write(1.0, 1.0)
    hardware_stop(I2CBus(chip, 1), ADDR)
    assert chip.all_off()


# ---- open_drive from config --------------------------------------------------------------


def test_open_drive_builds_the_configured_layout(tmp_path) -> None:
    state = tmp_path / "chip.json"
    drive = open_drive(MotorsConfig(layout="adafruit_motorhat", emulator=str(state)))
    assert isinstance(drive, MotorHatDrive)
    drive.write(0.5, 0.0)
    assert PCA9685Emulator(state_file=state).channel(9).duty == pytest.approx(0.5, abs=STEP)


def test_open_drive_without_a_board_is_a_usage_error(tmp_path) -> None:
    state = tmp_path / "chip.json"
    PCA9685Emulator(0x40, state_file=state)  # the board answers at another address
    with pytest.raises(UsageError, match=r"no motor board \(waveshare\) .* bus 1 at address 0x60"):
        open_drive(MotorsConfig(i2c_retries=0, emulator=str(state)))


def test_motorkit_imports_where_blinka_does_not_know_the_board(tmp_path) -> None:
    fake = tmp_path / "fake"
    fake.mkdir()
    for name in ("board", "busio"):
        (fake / f"{name}.py").write_text('raise NotImplementedError("Board not supported")\n')
    code = (
        "from jetbot_rt.hal.i2c import I2CBus\n"
        "from jetbot_rt.hal.motors import MotorHatDrive\n"
        "from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator\n"
        "chip = PCA9685Emulator(0x60)\n"
        "MotorHatDrive(I2CBus(chip, 1), 0x60, 1600.0, 1, 2).write(1.0, 0.0)\n"
        "print(chip.channel(9).duty)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
        env={"PYTHONPATH": str(fake), "PATH": "/usr/bin:/bin"},
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "1.0"


class TestPwmFrequencyAndReadBack:
    """The prescaler from the datasheet's formula, its limits, and MODE1 read back."""

    @pytest.mark.parametrize(("hz", "prescale"), [
        (200.0, 0x1E),  # the datasheet's own example
        (1600.0, 3), (50.0, 121), (60.0, 101),
        (1526.0, 3), (5000.0, 3),  # the fastest the chip does: prescale 3
        (24.0, 253), (23.84, 255), (10.0, 255),  # the slowest: 255
    ])
    def test_prescale(self, hz: float, prescale: int) -> None:
        assert prescale_for(hz) == prescale

    def test_the_chip_runs_at_the_configured_frequency(self, chip) -> None:
        WaveshareDrive(I2CBus(chip, 1), ADDR, 50.0)
        assert chip.registers[PRE_SCALE] == 121
        assert chip.frequency == pytest.approx(50.0, rel=0.01)
        assert not chip.sleeping

    def test_mode1_reads_back_awake_with_auto_increment(self, chip, waveshare) -> None:
        assert read_mode1(waveshare.bus, ADDR) == MODE1_AI


@pytest.mark.parametrize(("left", "right", "pwm"), [(1, 2, (8, 13)), (3, 4, (2, 7)),
                                                    (2, 1, (13, 8)), (4, 3, (7, 2))])
def test_motorhat_every_motors_enable_comes_back_after_a_stop(chip, left, right, pwm) -> None:
    drive = motorhat(chip, left=left, right=right)
    drive.write(0.5, 0.5)
    drive.stop()
    assert chip.all_off()
    drive.write(0.25, -0.25)
    # effective duty, not the full-on bit alone: the stop's full-off bit would win over it
    assert chip.channel(pwm[0]).duty == 1.0 and chip.channel(pwm[1]).duty == 1.0
    assert not chip.all_off()


# ---- the earlier Waveshare revision: outputs 8-13, driven as NVIDIA's jetbot drove it -----

# Before jetbot's commit "Handle the new revision of Waveshare board", jetbot drove the
# Waveshare board through Adafruit_MotorHAT: left = MotorHAT motor 1 (PWM 8, IN2 9, IN1 10),
# right = motor 2 (PWM 13, IN2 12, IN1 11), and a positive value ran BACKWARD: IN2 on, IN1 off.
JETBOT_FORWARD_IN2 = (9, 12)
JETBOT_FORWARD_IN1 = (10, 11)


def test_older_waveshare_revision_as_documented_matches_jetbots_writes(chip) -> None:
    """docs/HARDWARE.md: layout = "adafruit_motorhat", sign = [1, -1] drives outputs 8-13
    in jetbot's directions (MotorKit's motor2 turns the other way from the old library's)."""
    from jetbot_rt.runtime.actions import ActionPipeline

    actions = ActionPipeline(max_speed=0.5, sign=(1, -1))
    drive = motorhat(chip)
    drive.write(*actions.duties([1.0, 1.0]))  # forward
    assert chip.channel(8).full_on and chip.channel(13).full_on  # the enables
    assert outputs(chip, JETBOT_FORWARD_IN2) == pytest.approx([0.5, 0.5], abs=STEP)
    assert outputs(chip, JETBOT_FORWARD_IN1) == [0.0, 0.0]
    drive.write(*actions.duties([-1.0, -1.0]))  # reverse: IN1 active, as jetbot's FORWARD
    assert outputs(chip, JETBOT_FORWARD_IN1) == pytest.approx([0.5, 0.5], abs=STEP)
    assert outputs(chip, JETBOT_FORWARD_IN2) == [0.0, 0.0]
    assert chip.duties()[:4] == [0.0] * 4  # nothing on the newer revision's outputs


@pytest.mark.parametrize("layout", ["waveshare", "motorhat"])
def test_a_drive_whose_chip_was_put_to_sleep_faults_and_stays_off(chip, layout) -> None:
    from jetbot_rt.hal.motors import BoardAsleep, stop_and_sleep

    drive = WaveshareDrive(I2CBus(chip, 1), ADDR, 1600.0) if layout == "waveshare" \
        else motorhat(chip)
    drive.write(0.5, 0.5)
    stop_and_sleep(I2CBus(chip, 1), ADDR)  # jetbot-rt stop from another process
    assert chip.sleeping and chip.all_off()
    with pytest.raises(BoardAsleep):
        drive.write(0.5, 0.5)
    assert chip.sleeping and chip.all_off()


def test_waveshare_setup_sets_totem_pole_outputs_whatever_mode2_held(chip) -> None:
    from jetbot_rt.testing.pca9685_emulator import MODE2

    chip.registers[MODE2] = 0x00  # open-drain, left by another program
    WaveshareDrive(I2CBus(chip, 1), ADDR, 1600.0)
    assert chip.registers[MODE2] == 0x04
