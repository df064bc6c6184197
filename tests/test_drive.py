"""``jetbot-rt drive`` end to end, as a person runs it: the keyboard through a real pty, the
scripted person taking over from the bundled seek policy with ``--record``, signals and a
closed terminal while a person drives, and bad input refused before any motor moves."""

from __future__ import annotations

import argparse
import os
import pty
import signal
import subprocess
import termios
import time
from pathlib import Path

import pytest

from jetbot_rt.commands.drive import check_arguments
from jetbot_rt.errors import UsageError
from jetbot_rt.recording.reader import Recording
from jetbot_rt.runtime.policy import bundled_policy_path
from tests.runner import JETBOT_RT, read_telemetry, read_telemetry_safe, wait_for

pytest.importorskip("pybullet")

HANG_S = 60.0
"""Waits that only catch a hang (the machine is shared and loaded)."""
DEADMAN = "0.2"


def start_on_pty(tmp_path: Path, *extra: str) -> tuple[subprocess.Popen, int, int, Path]:
    """A sim drive whose stdin is a fresh pty (not its controlling terminal: a closed terminal
    shows as a read error, not SIGHUP); stdout and stderr to files."""
    master, slave = pty.openpty()
    telemetry = tmp_path / "telemetry.jsonl"
    with open(tmp_path / "out", "w") as out, open(tmp_path / "err", "w") as err:
        proc = subprocess.Popen(
            [JETBOT_RT, "drive", "--backend", "sim", "--input", "keyboard", "--deadman",
             DEADMAN, "--telemetry", str(telemetry), *extra],
            stdin=slave, stdout=out, stderr=err, start_new_session=True)
    return proc, master, slave, telemetry


def ticks(telemetry: Path) -> list[dict]:
    return [r for r in read_telemetry_safe(telemetry) if "tick" in r]


def hold(master: int, key: bytes, telemetry: Path, driven: int) -> None:
    """Send ``key`` as a terminal's auto-repeat does (every 33 ms) until ``driven`` ticks
    ran with it."""
    deadline = time.monotonic() + HANG_S
    command = {b"w": [1.0, 1.0], b"a": [-0.6, 0.6]}[key]
    while sum(1 for t in ticks(telemetry) if t.get("human") == command) < driven:
        assert time.monotonic() < deadline, "the key never drove the wheels"
        os.write(master, key)
        time.sleep(0.033)


def test_a_held_key_drives_a_released_one_stops_and_sigterm_ends_it_in_order(tmp_path):
    proc, master, slave, telemetry = start_on_pty(tmp_path)
    try:
        hold(master, b"w", telemetry, 15)
        released = len(ticks(telemetry))
        assert wait_for(lambda: len(ticks(telemetry)) > released + 20, HANG_S)
        hold(master, b"a", telemetry, 5)  # a person drives again
        os.write(master, b"a")
        proc.send_signal(signal.SIGTERM)
        proc.wait(HANG_S)
        restored = termios.tcgetattr(slave)[3] & termios.ICANON
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
        os.close(slave)
    records = read_telemetry(telemetry)
    tick_records = [r for r in records if "tick" in r]
    assert proc.returncode == 0, (tmp_path / "err").read_text()
    assert restored, "the terminal was left in non-canonical mode"
    forward = [t for t in tick_records if t["human"] == [1.0, 1.0]]
    assert forward and all(t["cmd"][0] > 0 and t["driver"] == "human" for t in forward)
    # after the release: zero, once the last key's deadman ran out
    after = tick_records[released:released + 20]
    assert after[-1]["human"] is None and after[-1]["cmd"] == [0.0, 0.0]
    stop = next(r for r in records if r.get("event") == "safe_stop")
    assert stop["reason"] == "SIGTERM received" and stop["fault"] is False
    assert [-0.6, 0.6] in [t["human"] for t in tick_records[released + 20:]]
    assert "drive:" in (tmp_path / "out").read_text()


def test_a_closed_terminal_while_a_person_drives_stops_the_wheels_with_exit_3(tmp_path):
    proc, master, slave, telemetry = start_on_pty(tmp_path)
    try:
        hold(master, b"w", telemetry, 10)
        os.write(master, b"w")
        os.close(master)
        master = -1
        proc.wait(HANG_S)
    finally:
        if proc.poll() is None:
            proc.kill()
        if master >= 0:
            os.close(master)
        os.close(slave)
    records = read_telemetry(telemetry)
    assert proc.returncode == 3
    lost = [r for r in records if r.get("event") == "input_lost"]
    assert len(lost) == 1 and "keyboard" in lost[0]["reason"]
    stop = next(r for r in records if r.get("event") == "safe_stop")
    assert stop["reason"].startswith("input lost: keyboard") and stop["cmd"] == [0.0, 0.0]
    assert "motors       confirmed zero" in (tmp_path / "out").read_text()


def test_the_scripted_person_takes_over_from_a_failing_policy_and_the_recording_marks_it(
        tmp_path):
    world = tmp_path / "hidden.toml"
    world.write_text("[sim]\ntask = \"seek\"\nlens = \"pinhole\"\ncamera_vfov_deg = 80.0\n"
                     "camera_pitch_deg = 32.0\nblock_color = [0.85, 0.4, 0.1]\n"
                     "floor_color = [0.3, 0.32, 0.3]\nfloor_texture = \"plain\"\n"
                     "[randomize]\nenabled = false\n")
    result = subprocess.run(
        [JETBOT_RT, "drive", "--backend", "sim", "--input", "scripted", "--config", str(world),
         "--policy", str(bundled_policy_path("seek")), "--duration", "3",
         "--record", str(tmp_path / "rec")],
        capture_output=True, text=True, timeout=HANG_S)
    assert result.returncode == 0, result.stderr
    recording = Recording.open(tmp_path / "rec")
    assert recording.meta["source"] == "jetbot-rt drive" and recording.meta["version"] == 2
    assert recording.meta["drive"]["input"] == "scripted"
    assert recording.meta["drive"]["reaction_s"] > 0  # the stand-in person's settings
    drivers = {t["driver"] for t in recording.ticks}
    # the takeover came at tick 34, the episode's end at tick 63 (of 90)
    assert drivers == {"policy", "human"}, "3 s in that world need a takeover"
    human = [t for t in recording.ticks if t["driver"] == "human"]
    assert all(t["human"] is not None and t["mu"] == pytest.approx(t["human"], abs=1e-4)
               for t in human)
    assert all("policy_mu" in t for t in recording.ticks)
    names = [e["event"] for e in recording.events]
    assert "takeover" in names and "episode_end" in names
    assert "takeovers" in result.stdout


@pytest.mark.parametrize(("given", "line"), [
    ({"input": "scripted", "backend": "real"}, "needs --backend sim"),
    ({"deadman": 0.5}, "--deadman must be in"),
    ({"deadman": 0.0}, "--deadman must be in"),
    ({"deadman": 0.30000001}, "got 0.30000001$"),  # as given: 0.3 would look inside the bound
])
def test_arguments_that_cannot_work_are_refused_at_configure(given, line):
    args = argparse.Namespace(**{"input": "keyboard", "backend": "sim", "deadman": 0.2,
                                 **given})
    with pytest.raises(UsageError, match=line):
        check_arguments(args)


@pytest.mark.parametrize(("args", "line"), [
    (["--input", "keyboard", "--backend", "sim"], "needs a terminal on stdin"),
    (["--input", "gamepad", "--backend", "sim", "--gamepad-device", "/nonexistent/js0"],
     "--gamepad-device /nonexistent/js0"),
    (["--input", "scripted", "--backend", "sim"], "task 'forward' has no privileged expert"),
    (["--input", "page", "--backend", "sim"], "it needs --monitor"),
])
def test_bad_input_is_one_line_and_exit_2_before_any_motor_or_file(args, line, tmp_path):
    record = tmp_path / "rec"
    result = subprocess.run([JETBOT_RT, "drive", *args, "--record", str(record)],
                            stdin=subprocess.DEVNULL, capture_output=True, text=True,
                            timeout=HANG_S)
    assert result.returncode == 2
    assert line in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "driving" not in result.stdout
    assert not record.exists(), "bad input left a recording behind"
