"""The PCA9685's register map (NXP datasheet, rev. 4): the one definition the motor drivers
(``hal/motors.py``) and the register-level emulator (``jetbot_rt.testing``) share."""

MODE1 = 0x00
MODE2 = 0x01
LED0_ON_L = 0x06
"""LEDn_ON_L, ON_H, OFF_L, OFF_H of channel n start at ``LED0_ON_L + 4 * n``."""
LAST_LED_REGISTER = 0x45  # LED15_OFF_H
ALL_LED_ON_L = 0xFA
ALL_LED_OFF_H = 0xFD
PRE_SCALE = 0xFE

MODE1_RESTART = 0x80
MODE1_AI = 0x20  # register auto-increment
MODE1_SLEEP = 0x10  # oscillator off
MODE1_ALLCALL = 0x01
MODE2_OUTDRV = 0x04  # totem-pole outputs
FULL_BIT = 0x10  # bit 4 of LEDn_ON_H (full on) and of LEDn_OFF_H (full off)

OSCILLATOR_HZ = 25_000_000
CHANNELS = 16
