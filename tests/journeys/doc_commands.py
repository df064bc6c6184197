"""The documented commands, read from the docs when a journey runs: a journey names a doc and
the start of a command in one of its fenced blocks, and runs what the doc says now. A doc edit
that drops or renames a command fails the journey (and ``test_every_journeys_commands_are_
still_in_their_docs``, in the fast suite, for the long journeys too); one that changes its
arguments is run as written.

Knobs (``with_knobs``): the only changes a journey makes to a command, each to a text that must
be in it: fewer steps, episodes or seconds where the doc's command has such a flag, a
temporary path for a fixed one (``/tmp/chip.json``, ``/mnt/jetbot``, ``/etc/jetbot-rt/config.toml``;
the robot's installed ``sudo /opt/jetbot-rt/bin/jetbot-rt`` as this checkout's ``jetbot-rt``
where the emulated board stands in for the robot's), port 0 (any free one) for a fixed port, and
the seed a doc's comment gives a repeated command (``world_N.toml``).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
"""The venv the suite runs in: its ``jetbot-rt``, ``jetbot-train`` and ``python`` come first."""
SHELL_LANGS = ("", "sh", "bash", "shell", "console")

# Each journey: (doc, the start of one of its commands). The docs site helper moves
# commands between README.md and docs/: a moved command fails here, naming where it went.
JOURNEYS: dict[str, list[tuple[str, str]]] = {
    "drive the simulator (README)": [
        ("README.md", "python3 -m venv .venv && .venv/bin/pip install -e '.[sim]'"),
    ],
    "train, evaluate, compare with a blind camera (README)": [
        ("README.md", "jetbot-train train --task seek --out runs/seek"),
        ("README.md", "jetbot-train eval --task seek --policy runs/seek/policy.onnx "
                      "--episodes 100"),
        ("README.md", "jetbot-train eval --task seek --policy runs/seek/policy.onnx --episodes 50 "
                      "--ablate blank"),
        ("README.md", "jetbot-train eval --task seek --policy runs/seek/policy.onnx --episodes 3 "
                      "--video evals"),
    ],
    "record, report, replay (README)": [
        ("README.md", "jetbot-rt run --backend sim --duration 20 --record rec"),
        ("README.md", "jetbot-rt report rec"),
        ("README.md", "jetbot-rt replay rec --policy new.onnx"),
    ],
    "the robot on the emulated board (docs/HARDWARE.md)": [
        ("docs/HARDWARE.md", "jetbot-rt run --backend real --config dry.toml --board-emulator"),
        ("docs/HARDWARE.md", "python -c \"from jetbot_rt.testing.pca9685_emulator import"),
        ("docs/HARDWARE.md", "jetbot-rt stop --config dry.toml --board-emulator"),
        ("docs/HARDWARE.md", "jetbot-rt check --config dry.toml --board-emulator"),
    ],
    "stage the service for the robot (docs/ROBOT.md)": [
        ("docs/ROBOT.md", "jetbot-rt install-service --root /mnt/jetbot"),
        ("docs/ROBOT.md", "systemd-sysusers --root=/mnt/jetbot"),
        ("docs/ROBOT.md", "systemd-analyze --root=/mnt/jetbot verify"),
    ],
    "calibrate the drive in the simulator (docs/CALIBRATION.md)": [
        ("docs/CALIBRATION.md", "jetbot-rt calibrate --backend sim --config TRUTH.toml --yes"),
    ],
    "calibrate the lens in the simulator (docs/CALIBRATION.md)": [
        ("docs/CALIBRATION.md", "jetbot-rt calibrate --camera --backend sim --config TRUTH.toml"),
    ],
    "drive, take over, fine-tune, evaluate in the simulator (docs/DRIVE.md)": [
        ("docs/DRIVE.md", "jetbot-rt drive --backend sim --input scripted --config world_1.toml"),
        ("docs/DRIVE.md", "jetbot-rt drive --backend sim --input scripted --config world_4.toml"),
        ("docs/DRIVE.md", "jetbot-train finetune --recordings hand_4 hand_5 hand_6 takeover_1"),
        ("docs/DRIVE.md", "jetbot-train eval --task seek --episodes 100 --num-envs 2 --seed 10000 "
                          "--json --policy ft_mix/policy.onnx --config"),
    ],
    "watch the policy on the emulated board's live page (docs/REAL_DATA.md)": [
        ("docs/REAL_DATA.md", "sudo /opt/jetbot-rt/bin/jetbot-rt run --backend real --config "
                              "/etc/jetbot-rt/config.toml --board-emulator /tmp/chip.json "
                              "--monitor 8080"),
        ("docs/HARDWARE.md", "python -c \"from jetbot_rt.testing.pca9685_emulator import"),
    ],
    "your own task (docs/TASKS.md)": [
        ("docs/TASKS.md", "jetbot-train train --task examples/tasks/my_task.py:ParkAtBlueWall"),
        ("docs/TASKS.md", "jetbot-train eval --task examples/tasks/my_task.py:ParkAtBlueWall"),
        ("docs/TASKS.md", "printf '[sim]\\ntask = \"examples/tasks/my_task.py:"),
        ("docs/TASKS.md", "jetbot-rt run --backend sim --config park.toml"),
    ],
}
PYTHON_BLOCKS: dict[str, list[tuple[str, str]]] = {
    "bring your own policy (docs/BRING_YOUR_OWN_POLICY.md)": [
        ("docs/BRING_YOUR_OWN_POLICY.md", "export_policy(model, \"my_policy.onnx\""),
    ],
}


def blocks(doc: str) -> list[tuple[str, list[str]]]:
    """The fenced blocks of ``doc`` (relative to the repository): (language, lines)."""
    found: list[tuple[str, list[str]]] = []
    lang: str | None = None
    lines: list[str] = []
    for line in (REPO / doc).read_text().splitlines():
        fence = re.match(r"\s*```(\w*)", line)
        if fence and lang is None:
            lang, lines = fence.group(1), []
        elif fence:
            found.append((lang, lines))
            lang = None
        elif lang is not None:
            lines.append(line)
    return found


def _without_comment(line: str) -> str:
    """The command before a shell comment (`` # ...`` outside quotes)."""
    quote = None
    for index, char in enumerate(line):
        if quote:
            quote = None if char == quote else quote
        elif char in "'\"":
            quote = char
        elif char == "#" and index > 0 and line[index - 1].isspace():
            return line[:index].rstrip()
    return line.rstrip()


def commands(doc: str) -> list[str]:
    """Every command of ``doc``'s shell blocks, continuation lines joined, comments cut."""
    found = []
    for lang, lines in blocks(doc):
        if lang not in SHELL_LANGS:
            continue
        pending = ""
        for line in lines:
            text = _without_comment(line)
            if text.endswith("\\"):
                pending += text[:-1].rstrip() + " "
                continue
            text = (pending + text.strip()).strip()
            pending = ""
            if text:
                found.append(text)
    return found


def command(doc: str, start: str) -> str:
    """The one command of ``doc`` that starts with ``start``, as the doc has it now."""
    matches = [c for c in commands(doc) if c.startswith(start)]
    if len(matches) == 1:
        return matches[0]
    if matches:
        raise AssertionError(f"{doc}: {len(matches)} commands start with {start!r}: {matches}")
    elsewhere = [str(p.relative_to(REPO)) for p in [REPO / "README.md", *sorted(
        (REPO / "docs").glob("*.md"))] if any(c.startswith(start) for c in commands(
            str(p.relative_to(REPO))))]
    raise AssertionError(f"{doc} has no command starting with {start!r} any more (a journey "
                         f"runs it: tests/journeys/doc_commands.py); found in: {elsewhere}")


TOML_BLOCKS: dict[str, list[tuple[str, str]]] = {
    "calibrate the drive in the simulator (docs/CALIBRATION.md)": [
        ("docs/CALIBRATION.md", "motor_gain = 19.854"),
    ],
    "calibrate the lens in the simulator (docs/CALIBRATION.md)": [
        ("docs/CALIBRATION.md", "lens_focal = 1.02024"),
    ],
}
"""The TOML the docs show: a journey writes the block as a file (``toml_block``)."""


def python_block(doc: str, containing: str, lang: str = "python") -> str:
    """The one Python (or ``lang``) block of ``doc`` that contains ``containing``."""
    matches = ["\n".join(lines) + "\n" for found, lines in blocks(doc)
               if found == lang and any(containing in line for line in lines)]
    assert len(matches) == 1, f"{doc}: {len(matches)} {lang} blocks contain {containing!r}"
    return matches[0]


def toml_block(doc: str, containing: str) -> str:
    """The one TOML block of ``doc`` that contains ``containing``."""
    return python_block(doc, containing, lang="toml")


INLINE: dict[str, list[tuple[str, str]]] = {
    "the GUI without a display (docs/RUN.md)": [
        ("docs/RUN.md", "xvfb-run -a jetbot-rt run --backend sim --gui --duration 20"),
    ],
    "bring your own policy (docs/BRING_YOUR_OWN_POLICY.md)": [
        ("docs/BRING_YOUR_OWN_POLICY.md", "jetbot-rt run --backend sim --policy my_policy.onnx "
                                          "--duration 10"),
    ],
    "train, evaluate, compare with a blind camera (README)": [
        ("README.md", "jetbot-rt report evals/episode-10000"),
    ],
    "the robot on the emulated board (docs/HARDWARE.md)": [
        ("docs/HARDWARE.md", '[camera] source = "gst:videotestsrc is-live=true"'),
    ],
    "drive, take over, fine-tune, evaluate in the simulator (docs/DRIVE.md)": [
        ("docs/DRIVE.md", "3 drives of 200 s (seeds 1-3), then hand drives of 110 s (4-6)"),
        ("docs/DRIVE.md", "(`world_N.toml` is `hidden_world.toml` with `seed = N` under "
                          "`[sim]`.)"),
    ],
    "watch the policy on the emulated board's live page (docs/REAL_DATA.md)": [
        ("docs/REAL_DATA.md", 'Set `[policy] path = "/etc/jetbot-rt/policy.onnx"` in '
                              "`/etc/jetbot-rt/config.toml`"),
        ("docs/HARDWARE.md", '[camera] source = "gst:videotestsrc is-live=true"'),
        ("docs/MONITOR.md", "| `POST /stop` | latches the safe stop as `jetbot-rt stop` does; "
                            "the run ends orderly (exit 0, `stopped stop from the monitor page "
                            "(ADDR)`) |"),
    ],
}
"""Commands and settings the docs give in running text: ``text`` must be in the doc (line
breaks and indentation read as one space)."""


def inline(doc: str, text: str) -> str:
    """``text``, once checked to be in ``doc`` as written."""
    words = " ".join((REPO / doc).read_text().split())
    assert text in words, f"{doc} no longer says {text!r} (a journey runs it)"
    return text


def with_knobs(text: str, knobs: Mapping[str, str]) -> str:
    for old, new in knobs.items():
        assert old in text, f"the knob {old!r} is not in the documented command: {text}"
        text = text.replace(old, new)
    return text


def environment(**extra: str) -> dict[str, str]:
    """This venv's programs first on PATH: the documented ``jetbot-rt`` is this checkout's."""
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    env.update(extra)
    return env


def sh(text: str, cwd: Path, timeout: float = 120,
       env: Mapping[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """``text`` run by bash in ``cwd``, as a person pastes it."""
    return subprocess.run(["bash", "-c", text], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, env=dict(env or environment()))


def ok(proc: subprocess.CompletedProcess[str]) -> subprocess.CompletedProcess[str]:
    assert proc.returncode == 0, (proc.args, proc.returncode, proc.stdout[-3000:],
                                  proc.stderr[-3000:])
    return proc
