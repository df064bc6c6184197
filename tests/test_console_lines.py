"""What ``jetbot-rt`` prints reaches its reader in whole lines, and a closed standard stream
costs output, never the run (docs/SAFETY.md, "Untrusted input and sure exits").

stdout and stderr that share one file (the journal, ``2>&1``) get one writer, and each
thread's text is held until its newline (``print`` writes the text and the newline apart):
lines of two streams, or of two threads, never run together. A run started with stdout or
stderr closed drives as any other: ``/dev/null`` holds the closed number, so nothing the run
opens later (the motor board, a recording) takes fd 1 or 2.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from fault_helpers import live_camera, needs_gst, real_config
from runner import JETBOT_RT

from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

LIVENESS_S = 60.0
LINES = 1500

MANY_WRITERS = f"""
import sys, threading
from jetbot_rt.service import console
def say(stream, name):
    for i in range({LINES}):
        print(name, i, "x" * (i % 97), "end", file=getattr(sys, stream))
with console.unblocked():
    threads = [threading.Thread(target=say, args=(stream, f"{{stream}}{{n}}"))
               for stream in ("stdout", "stderr") for n in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
"""
WHOLE = re.compile(r"(stdout|stderr)(\d) (\d+) (x*) end")


def check_whole_lines(text: str) -> None:
    seen: dict[str, list[int]] = {}
    for line in text.splitlines():
        match = WHOLE.fullmatch(line)
        assert match, f"a line run together with another: {line[:200]!r}"
        assert len(match[4]) == int(match[3]) % 97, line
        seen.setdefault(match[1] + match[2], []).append(int(match[3]))
    # every line, once, and each thread's in its order
    assert seen == {name: list(range(LINES)) for name in
                    ("stdout0", "stdout1", "stderr0", "stderr1")}


@pytest.mark.parametrize("target", ["file", "pipe"])
def test_lines_of_two_streams_and_four_threads_on_one_file_never_run_together(
        tmp_path: Path, target: str) -> None:
    command = [sys.executable, "-c", MANY_WRITERS]
    if target == "pipe":
        done = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              timeout=LIVENESS_S)
        output = done.stdout
    else:
        with open(tmp_path / "journal", "wb") as journal:
            done = subprocess.run(command, stdout=journal, stderr=subprocess.STDOUT,
                                  timeout=LIVENESS_S)
        output = (tmp_path / "journal").read_bytes()
    assert done.returncode == 0
    check_whole_lines(output.decode())


def test_text_without_a_newline_is_written_on_flush_and_at_the_exit() -> None:
    code = ("import sys\nfrom jetbot_rt.service import console\n"
            "with console.unblocked():\n"
            "    print('progress ', end='', flush=True)\n"
            "    print('50%', end='')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=LIVENESS_S)
    assert (done.returncode, done.stdout, done.stderr) == (0, "progress 50%", "")


@pytest.mark.parametrize("closed", ["0", "1", "2"])
def test_a_closed_standard_descriptor_is_held_by_dev_null_so_no_file_takes_its_number(
        tmp_path: Path, closed: str) -> None:
    code = ("import json, os, sys\nfrom jetbot_rt.service import console\n"
            "with console.unblocked():\n"
            "    fd = os.open(sys.argv[1], os.O_WRONLY | os.O_CREAT, 0o600)\n"
            "    names = [os.readlink(f'/proc/self/fd/{n}') for n in (0, 1, 2)]\n"
            "    with open(sys.argv[1] + '.names', 'w') as out:\n"
            "        out.write(json.dumps([fd, names]))\n")
    done = subprocess.run(["bash", "-c", f'exec "$@" {closed}>&-', "bash", sys.executable,
                           "-c", code, str(tmp_path / "opened")],
                          capture_output=True, text=True, timeout=LIVENESS_S)
    assert done.returncode == 0, done.stderr
    fd, names = json.loads((tmp_path / "opened.names").read_text())
    assert fd > 2 and names[int(closed)] == os.devnull


def dry_run(tmp_path: Path, redirect: str) -> subprocess.CompletedProcess[str]:
    config = tmp_path / "dry.toml"
    config.write_text(real_config(live_camera("closedstd")))
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "rt"))
    (tmp_path / "rt").mkdir(mode=0o700)
    command = [JETBOT_RT, "run", "--backend", "real", "--config", str(config),
               "--board-emulator", str(tmp_path / "chip.json"), "--duration", "0.5",
               "--telemetry", str(tmp_path / "t.jsonl")]
    return subprocess.run(["bash", "-c", f'exec "$@" {redirect}', "bash", *command],
                          capture_output=True, text=True, timeout=LIVENESS_S, env=env)


def drove_and_stopped(tmp_path: Path) -> bool:
    ticks = [line for line in (tmp_path / "t.jsonl").read_text().splitlines()
             if '"tick"' in line]
    with PCA9685Emulator(state_file=tmp_path / "chip.json") as chip:
        return len(ticks) > 5 and chip.all_off()


@needs_gst
def test_a_run_with_stderr_closed_drives_and_prints_its_summary(tmp_path: Path) -> None:
    """No stack dumps (they have nowhere to go) and no messages: the exit code speaks."""
    done = dry_run(tmp_path, "2>&-")
    assert done.returncode == 0, done.stdout
    assert "jetbot-rt run summary" in done.stdout and "exit code    0" in done.stdout
    assert drove_and_stopped(tmp_path)


@needs_gst
def test_a_run_with_stdout_closed_drives_and_says_its_summary_was_lost(tmp_path: Path) -> None:
    done = dry_run(tmp_path, ">&-")
    assert done.returncode == 0, done.stderr
    assert done.stderr.splitlines()[-1].startswith("jetbot-rt: stdout: ")
    assert done.stderr.splitlines()[-1].endswith(" bytes not written (stdout was closed)")
    assert drove_and_stopped(tmp_path)
