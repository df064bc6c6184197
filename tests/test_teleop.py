"""The hand inputs of ``jetbot-rt drive`` on their own: the arbiter's deadman and takeover
marks, the keyboard on a real pty, the gamepad on a FIFO fed real ``js_event`` records."""

from __future__ import annotations

import os
import pty
import struct
import termios
import time

import numpy as np
import pytest

from jetbot_rt.errors import UsageError
from jetbot_rt.teleop.gamepad import (
    EVENT,
    JS_EVENT_AXIS,
    JS_EVENT_BUTTON,
    JS_EVENT_INIT,
    GamepadInput,
)
from jetbot_rt.teleop.hand import Arbiter, HandCommand, HandInput
from jetbot_rt.teleop.keyboard import KeyboardInput, split_keys

IMAGE = np.zeros((4, 4, 3), np.uint8)
HANG_S = 5.0
"""Waits that only catch a hang (generous: the machine is shared)."""


class Fixed:
    def __init__(self, mu: tuple[float, float]) -> None:
        self.mu = np.asarray(mu, np.float32)

    def infer(self, image: np.ndarray) -> np.ndarray:
        return self.mu


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def wait_for(condition, what: str) -> None:
    deadline = time.monotonic() + HANG_S
    while not condition():
        assert time.monotonic() < deadline, f"no {what} within {HANG_S} s"
        time.sleep(0.01)


def test_a_hand_command_older_than_the_deadman_is_zero_when_the_person_drives_alone():
    clock = Clock()
    hand = HandInput(deadman_s=0.25, clock=clock)
    arbiter = Arbiter(None, hand, clock)
    hand.propose(HandCommand((1.0, 1.0)))
    clock.now += 0.25
    assert list(arbiter.infer(IMAGE)) == [1.0, 1.0]
    assert arbiter.marks == {"driver": "human", "human": [1.0, 1.0]}
    clock.now += 0.01
    assert list(arbiter.infer(IMAGE)) == [0.0, 0.0]
    assert arbiter.marks == {"driver": "human", "human": None}


def test_a_takeover_replaces_the_policy_while_held_and_hands_back_after_the_deadman():
    clock = Clock()
    hand = HandInput(deadman_s=0.2, clock=clock)
    arbiter = Arbiter(Fixed((0.5, 0.5)), hand, clock)
    assert list(arbiter.infer(IMAGE)) == [0.5, 0.5] and arbiter.switched is None
    hand.propose(HandCommand((0.0, 0.0)))  # the brake: a zero command that takes over
    assert list(arbiter.infer(IMAGE)) == [0.0, 0.0]
    assert arbiter.switched == "takeover"
    assert arbiter.marks == {"driver": "human", "human": [0.0, 0.0], "policy_mu": [0.5, 0.5]}
    clock.now += 0.3
    assert list(arbiter.infer(IMAGE)) == [0.5, 0.5]
    assert arbiter.switched == "handback" and arbiter.marks["driver"] == "policy"
    hand.propose(HandCommand((1.0, -1.0), takeover=False))  # a suggestion only
    assert list(arbiter.infer(IMAGE)) == [0.5, 0.5]
    assert (arbiter.takeovers, arbiter.human_ticks, arbiter.ticks) == (1, 1, 4)


def test_a_lost_input_calls_back_once_and_proposes_nothing_after():
    hand = HandInput()
    lost: list[str] = []
    hand.on_lost = lost.append
    hand.propose(HandCommand((1.0, 1.0)))
    hand.lost("gone")
    hand.lost("gone again")
    assert lost == ["gone"] and hand.command(time.monotonic()) is None


def test_arrow_keys_are_one_key_and_a_lone_escape_is_one_byte():
    assert split_keys(b"w\x1b[Ax\x1b") == [b"w", b"\x1b[A", b"x", b"\x1b"]


def test_the_keyboard_on_a_pty_holds_a_key_for_the_deadman_and_gives_the_terminal_back():
    master, slave = pty.openpty()
    try:
        before = termios.tcgetattr(slave)
        keyboard = KeyboardInput(slave, deadman_s=0.2)
        quits: list[str] = []
        keyboard.on_quit = quits.append
        keyboard.start()
        assert not termios.tcgetattr(slave)[3] & termios.ICANON
        os.write(master, b"zzw")  # unknown keys ignored, the last known one counts
        wait_for(lambda: keyboard.presses == 1, "key press")
        pressed = keyboard._at  # the press's own time: a loaded machine cannot age it here
        assert keyboard.command(pressed + 0.19) == HandCommand((1.0, 1.0))
        assert keyboard.command(pressed + 0.21) is None
        os.write(master, b"x")
        wait_for(lambda: quits, "quit")
        keyboard.close()
        assert termios.tcgetattr(slave) == before
    finally:
        os.close(master)
        os.close(slave)


def test_a_closed_terminal_is_a_lost_keyboard():
    master, slave = pty.openpty()
    keyboard = KeyboardInput(slave)
    lost: list[str] = []
    keyboard.on_lost = lost.append
    keyboard.start()
    try:
        os.close(master)
        wait_for(lambda: lost, "lost input")
        assert "keyboard: terminal read failed" in lost[0] or "closed" in lost[0]
    finally:
        keyboard.close()
        os.close(slave)


def test_the_keyboard_refuses_a_stdin_that_is_no_terminal(tmp_path):
    read, write = os.pipe()
    try:
        with pytest.raises(UsageError, match="needs a terminal on stdin"):
            KeyboardInput(read)
    finally:
        os.close(read)
        os.close(write)


def js(value: int, kind: int, number: int, ms: int = 0) -> bytes:
    return EVENT.pack(ms, value, kind, number)


@pytest.fixture
def pad(tmp_path):
    path = tmp_path / "js0"
    os.mkfifo(path)
    feed = os.open(path, os.O_RDWR)  # a writer that is there before the reader opens
    gamepad = GamepadInput(str(path), deadman_s=0.2)
    lost: list[str] = []
    gamepad.on_lost = lost.append
    gamepad.start()
    yield gamepad, feed, lost
    gamepad.close()
    os.close(feed)


def test_the_gamepad_drives_while_the_deadman_button_is_held_and_stops_on_release(pad):
    gamepad, feed, _ = pad
    assert EVENT.size == 8
    # the kernel's initial state, then the stick pushed up and right, then LB pressed
    os.write(feed, js(0, JS_EVENT_AXIS | JS_EVENT_INIT, 0) + js(0, JS_EVENT_AXIS | JS_EVENT_INIT, 1)
             + js(-32767, JS_EVENT_AXIS, 1) + js(8000, JS_EVENT_AXIS, 0)[:5])
    os.write(feed, js(8000, JS_EVENT_AXIS, 0)[5:])  # a record split across two reads
    assert gamepad.command(time.monotonic()) is None  # the stick alone does not drive
    os.write(feed, js(1, JS_EVENT_BUTTON, 4))
    wait_for(lambda: gamepad.command(time.monotonic()) is not None, "gamepad command")
    first = gamepad._at
    left, right = gamepad.command(first).mu
    assert left == 1.0 and right == pytest.approx(1 - 8000 / 32767)
    # longer than the deadman: the held button keeps it renewed (waited for, not slept on,
    # so a reader thread the loaded machine starves for a moment does not fail the test)
    wait_for(lambda: gamepad._at > first + 0.3, "renewal while held")
    assert gamepad.command(gamepad._at) is not None
    os.write(feed, js(0, JS_EVENT_BUTTON, 4))
    wait_for(lambda: gamepad.command(time.monotonic()) is None, "release")
    assert gamepad.events == 6


def test_the_gamepad_brake_button_takes_over_with_zero(pad):
    gamepad, feed, _ = pad
    os.write(feed, js(-32767, JS_EVENT_AXIS, 1) + js(1, JS_EVENT_BUTTON, 4)
             + js(1, JS_EVENT_BUTTON, 5))
    wait_for(lambda: gamepad.events == 3, "events")
    wait_for(lambda: gamepad.command(time.monotonic()) == HandCommand((0.0, 0.0)), "brake")


def test_an_unplugged_gamepad_is_a_lost_input(tmp_path):
    path = tmp_path / "js0"
    os.mkfifo(path)
    feed = os.open(path, os.O_RDWR)
    gamepad = GamepadInput(str(path))
    lost: list[str] = []
    gamepad.on_lost = lost.append
    gamepad.start()
    try:
        os.write(feed, js(1, JS_EVENT_BUTTON, 4))
        wait_for(lambda: gamepad.events == 1, "event")
        os.close(feed)  # the device's end closes: end of file, as an unplugged pad's read fails
        wait_for(lambda: lost, "lost input")
        assert "gamepad" in lost[0] and gamepad.command(time.monotonic()) is None
    finally:
        gamepad.close()


@pytest.mark.parametrize("make", ["missing", "regular"])
def test_a_gamepad_device_that_is_no_joystick_is_refused(tmp_path, make):
    path = tmp_path / "js9"
    if make == "regular":
        path.write_bytes(struct.pack("<IhBB", 0, 1, 1, 4))
    with pytest.raises(UsageError, match="--gamepad-device"):
        GamepadInput(str(path))
