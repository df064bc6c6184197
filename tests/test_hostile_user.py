"""A second local user against ``jetbot-rt stop``, the control socket's directory and the
emulator's state file (docs/SAFETY.md, "Untrusted input and sure exits").

The stop puts the chip to sleep before it asks any process anything, asks every socket it
trusts at once within ``ASK_TOTAL_S`` in all, and ignores (and names, in one line) whatever
another user made: their directory at our ``/tmp`` name, their sockets, a symbolic link. A
runtime whose ``/tmp/jetbot-rt-<uid>`` another user made first neither gives up nor talks
through that user's directory. Root never looks in ``/tmp``.

The other users are uids made up by each test (``hostile_user.py``): real processes with
that uid, not a mock of one. Those cases need root and are skipped without it.
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import policy_models
import pytest
from fault_helpers import live_camera, needs_gst, real_config, record_figures
from hostile_user import (
    as_user,
    command,
    needs_root,
    shared_dir,
    tmp_names,
    unused_uid,
    user_env,
)
from runner import read_telemetry_safe, wait_for

from jetbot_rt.hal.i2c import I2CBus
from jetbot_rt.hal.motors import WaveshareDrive
from jetbot_rt.service.stop_socket import ASK_TOTAL_S
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator

HANG_S = 20.0
"""Catches a hang only: a stop takes an interpreter start plus ``ASK_TOTAL_S``. The old stop
asked 40 silent sockets 0.5 s each, one after the other: 20 s."""
SILENT = 40

LISTENER = """
import select, socket, sys
chip_path, paths = sys.argv[1], sys.argv[2:]
chip = None
if chip_path != "-":
    from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator
    chip = PCA9685Emulator(state_file=chip_path)
listeners = []
for path in paths:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(path)
    s.listen(64)
    listeners.append(s)
print("ready", flush=True)
held, off = [], 0
while True:
    ready, _, _ = select.select(listeners + [sys.stdin], [], [])
    if sys.stdin in ready:
        break
    for s in ready:
        held.append(s.accept()[0])  # accepted, never answered
        if chip is not None:
            off += chip.refresh().all_off() and chip.sleeping
print(len(held), off, flush=True)
"""
"""Sockets that accept and never answer; at the end, how many connections came and how many
of them found the board already off and asleep."""

STOP_MODULES = ("jetbot_rt.cli", "jetbot_rt.commands.stop", "jetbot_rt.testing.pca9685_emulator",
                "smbus2", "socket")
RUN_MODULES = (*STOP_MODULES, "jetbot_rt.commands.run", "jetbot_rt.hal.real",
               "jetbot_rt.runtime.policy", "onnxruntime", "numpy")
CLI = "import sys\nfrom jetbot_rt.cli import main\nsys.exit(main(sys.argv[1:]))\n"


class Listener:
    """``LISTENER`` in a process of its own, as ``uid`` (None: this test's user)."""

    def __init__(self, paths: list[Path], uid: int | None = None, chip: Path | None = None):
        args = [str(chip) if chip else "-", *map(str, paths)]
        cmd = ([sys.executable, "-c", LISTENER, *args] if uid is None
               else command(uid, LISTENER, *args, modules=("select", "socket")))
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, cwd="/")
        assert self.proc.stdout is not None
        assert self.proc.stdout.readline().strip() == "ready"

    def finish(self) -> tuple[int, int]:
        """(connections accepted, of them with the board off and asleep)."""
        out, _ = self.proc.communicate("", timeout=30)
        accepted, off = out.split()
        return int(accepted), int(off)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()


def driven_board(path: Path) -> PCA9685Emulator:
    chip = PCA9685Emulator(0x60, state_file=path)
    WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0).write(0.6, 0.6)
    assert not chip.refresh().all_off()
    return chip


def stop_line(stderr: str, start: str) -> str:
    assert "Traceback" not in stderr, stderr
    (line,) = [x for x in stderr.splitlines() if x.startswith(f"jetbot-rt stop: {start}")]
    return line


# ---- 40 sockets that accept and never answer ----------------------------------------------


def test_forty_silent_sockets_are_asked_after_the_board_is_off_and_all_at_once(
        tmp_path: Path) -> None:
    """Every connection ``stop`` makes finds the board already off and asleep; the asking
    ends after ``ASK_TOTAL_S`` in all, and the 40 are one note line."""
    run_dir = tmp_path / "run"
    run_dir.mkdir(mode=0o700)
    chip = driven_board(tmp_path / "chip.json")
    listener = Listener([run_dir / f"control-{n}.sock" for n in range(SILENT)],
                        chip=tmp_path / "chip.json")
    try:
        t0 = time.monotonic()
        stop = subprocess.Popen(
            [sys.executable, "-m", "jetbot_rt.cli", "stop", "--board-emulator",
             str(tmp_path / "chip.json")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(run_dir)))
        t_off = wait_for(lambda: chip.refresh().all_off(), HANG_S)
        out, err = stop.communicate(timeout=HANG_S)
        t_done = time.monotonic()
        accepted, off_when_asked = listener.finish()
    finally:
        listener.kill()
    assert stop.returncode == 0, out + err
    assert t_off is not None and t_done - t0 < HANG_S
    assert accepted == SILENT and off_when_asked == SILENT
    note = stop_line(err, "note:")
    assert f"could not ask {SILENT} runtime socket(s)" in note
    assert f"no answer within {ASK_TOTAL_S:g} s" in note and f"and {SILENT - 4} more" in note
    assert chip.refresh().all_off() and chip.sleeping
    record_figures("stop-40-silent-sockets", stop_to_board_off_s=round(t_off - t0, 4),
                   stop_done_s=round(t_done - t0, 4))


# ---- another user's directories and sockets -----------------------------------------------


@needs_root
def test_another_users_directory_at_our_tmp_name_is_ignored_and_named(tmp_path: Path) -> None:
    """User V has no runtime directory in the environment (sudo, cron): ``stop`` falls back to
    ``/tmp/jetbot-rt-V``, which user H made first, full of sockets that never answer, next to
    an H-owned ``/tmp/jetbot-rt-V.x`` and a link to H's directory. V's stop asks none of
    them, names them in one line, and the board is off."""
    victim, hostile = unused_uid(), unused_uid()
    with tmp_names(victim), tmp_names(hostile):
        taken = Path(f"/tmp/jetbot-rt-{victim}")
        assert as_user(hostile, "import os, sys\nos.mkdir(sys.argv[1], 0o777)\n"
                       "os.chmod(sys.argv[1], 0o777)\nos.mkdir(sys.argv[1] + '.x', 0o700)\n"
                       "os.symlink(sys.argv[1], sys.argv[1] + '.link')\n"
                       "os.mkdir(sys.argv[1] + '.\\n\\x1b[2J')\n",  # a newline, a terminal escape
                       str(taken)).returncode == 0
        board_dir = shared_dir(victim)
        try:
            chip = driven_board(board_dir / "chip.json")
            listener = Listener([taken / f"control-{n}.sock" for n in range(SILENT)], hostile)
            try:
                t0 = time.monotonic()
                stop = as_user(victim, CLI, "stop", "--board-emulator",
                               str(board_dir / "chip.json"), modules=STOP_MODULES)
                elapsed = time.monotonic() - t0
                accepted, _ = listener.finish()
            finally:
                listener.kill()
            assert stop.returncode == 0, stop.stdout + stop.stderr
            assert accepted == 0, "the stop talked to another user's sockets"
            assert elapsed < HANG_S
            line = stop_line(stop.stderr, "ignored")
            for why in (f"{taken} (owned by uid {hostile})",
                        f"{taken}.x (owned by uid {hostile})",
                        f"{taken}.link (a symbolic link)",
                        f"{taken}.\\x0a\\x1b[2J (owned by uid {hostile})"):
                assert why in line, line
            assert chip.refresh().all_off() and chip.sleeping
            assert os.stat(board_dir / "chip.json").st_uid == victim  # still V's
        finally:
            shutil.rmtree(board_dir)
    record_figures("stop-hostile-tmp-dir", stop_done_s=round(elapsed, 4))


@needs_root
def test_another_users_sockets_and_links_in_our_directory_are_not_asked(tmp_path: Path) -> None:
    run_dir = shared_dir(0)  # ours (root's), where H can reach it
    hostile = unused_uid()
    theirs = shared_dir(hostile)
    try:
        os.chmod(run_dir, 0o777)  # long enough for H to put sockets in it
        listener = Listener([run_dir / "control-1.sock", theirs / "control-2.sock"], hostile)
        os.chmod(run_dir, 0o700)
        (run_dir / "control-link.sock").symlink_to(theirs / "control-2.sock")
        chip = driven_board(tmp_path / "chip.json")
        try:
            stop = subprocess.run(
                [sys.executable, "-m", "jetbot_rt.cli", "stop", "--board-emulator",
                 str(tmp_path / "chip.json")], capture_output=True, text=True, timeout=HANG_S,
                env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(run_dir)))
            accepted, _ = listener.finish()
        finally:
            listener.kill()
    finally:
        shutil.rmtree(theirs)
        shutil.rmtree(run_dir)
    assert stop.returncode == 0, stop.stdout + stop.stderr
    assert accepted == 0
    line = stop_line(stop.stderr, "ignored")
    assert f"{run_dir}/control-1.sock (owned by uid {hostile})" in line
    assert f"{run_dir}/control-link.sock (a symbolic link)" in line
    assert chip.refresh().all_off()


@needs_root
def test_the_control_socket_answers_only_its_user_and_root(tmp_path: Path) -> None:
    """Even where the modes would let another user connect, the runtime's server reads the
    caller's uid (``SO_PEERCRED``) and does not stop for it."""
    from jetbot_rt.service.stop_socket import ControlServer

    hostile = unused_uid()
    run_dir = shared_dir(0)
    reasons: list[str] = []
    server = ControlServer(reasons.append, run_dir / "control.sock")
    server.start()
    try:
        os.chmod(run_dir, 0o755)
        os.chmod(server.path, 0o666)
        asked = as_user(hostile, "import socket, sys\n"
                        "s = socket.socket(socket.AF_UNIX)\ns.settimeout(5)\n"
                        "s.connect(sys.argv[1])\ns.sendall(b'stop\\n')\n"
                        "print(s.recv(64).decode().strip())\n", str(server.path),
                        modules=("socket",))
    finally:
        server.close()
        shutil.rmtree(run_dir)
    assert asked.stdout.strip() == "error not allowed", asked.stdout + asked.stderr
    assert reasons == []


# ---- a runtime whose /tmp directory another user made first -------------------------------


@needs_root
@needs_gst
def test_another_users_tmp_directory_neither_refuses_nor_intercepts_run(tmp_path: Path) -> None:
    """H makes ``/tmp/jetbot-rt-V`` first (mode 0777, sockets in it). V's ``run`` (it used to
    exit 2) drives from a private ``/tmp/jetbot-rt-V.XXXXXX`` instead, writes nothing into
    H's directory, and V's ``stop`` finds it there."""
    victim, hostile = unused_uid(), unused_uid()
    with tmp_names(victim), tmp_names(hostile):
        taken = Path(f"/tmp/jetbot-rt-{victim}")
        assert as_user(hostile, "import os, sys\nos.mkdir(sys.argv[1])\n"
                       "os.chmod(sys.argv[1], 0o777)\n", str(taken)).returncode == 0
        listener = Listener([taken / "control-1.sock"], hostile)
        work = shared_dir(victim)
        try:
            policy = policy_models.constant(work / "policy.onnx", (0.5, 0.5))
            config = work / "robot.toml"
            config.write_text(real_config(live_camera("h25run"))
                              + "[loop]\nwatchdog_timeout = 0.5\nmax_frame_age = 0.5\n")
            chip = PCA9685Emulator(0x60, state_file=work / "chip.json")
            telemetry = work / "t.jsonl"
            runtime = subprocess.Popen(
                command(victim, CLI, "run", "--backend", "real", "--policy", str(policy),
                        "--config", str(config), "--board-emulator", str(work / "chip.json"),
                        "--telemetry", str(telemetry), "--duration", "60",
                        modules=RUN_MODULES),
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd="/",
                env=user_env())
            try:
                ticking = wait_for(lambda: runtime.poll() is not None or sum(
                    "event" not in r for r in read_telemetry_safe(telemetry)) >= 10, 60, 0.05)
                assert ticking is not None and runtime.poll() is None, runtime.communicate()
                (own,) = [p for p in Path("/tmp").glob(f"jetbot-rt-{victim}.*")]
                st = os.lstat(own)
                assert stat.S_ISDIR(st.st_mode) and st.st_uid == victim
                assert stat.S_IMODE(st.st_mode) == 0o700
                assert [p.name for p in own.glob("control-*.sock")] == \
                    [f"control-{runtime.pid}.sock"]
                stop = as_user(victim, CLI, "stop", "--board-emulator", str(work / "chip.json"),
                               modules=STOP_MODULES)
                out, err = runtime.communicate(timeout=30)
            finally:
                if runtime.poll() is None:
                    runtime.kill()
                    runtime.communicate()
            accepted, _ = listener.finish()
            assert stop.returncode == 0, stop.stdout + stop.stderr
            assert "latched its safe stop" in stop.stdout  # it found V's runtime
            assert f"{taken} (owned by uid {hostile})" in stop_line(stop.stderr, "ignored")
            assert runtime.returncode == 0, out + err
            assert "Traceback" not in err
            assert accepted == 0 and sorted(p.name for p in taken.iterdir()) == \
                ["control-1.sock"]
            assert chip.refresh().all_off() and chip.sleeping
        finally:
            listener.kill()
            shutil.rmtree(work)


@needs_root
def test_a_runtime_directory_in_the_environment_that_is_not_ours_is_refused(
        tmp_path: Path) -> None:
    victim, hostile = unused_uid(), unused_uid()
    theirs = shared_dir(hostile)
    os.chmod(theirs, 0o777)
    work = shared_dir(victim)
    try:
        result = as_user(victim, CLI, "run", "--backend", "real", "--board-emulator",
                         str(work / "chip.json"), "--duration", "1", modules=RUN_MODULES,
                         env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(theirs)))
        listing = list(theirs.iterdir())
    finally:
        shutil.rmtree(theirs)
        shutil.rmtree(work)
    assert result.returncode == 2, result.stdout + result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert f"runtime directory {theirs} is owned by uid {hostile}" in line, line
    assert listing == []


@needs_root
def test_a_private_alternative_is_reused_and_a_link_is_never_followed() -> None:
    """The fallback a second time (another run) is the same private directory; H's link at
    the ``/tmp`` name, pointing at a directory of V's, is not followed either."""
    victim, hostile = unused_uid(), unused_uid()
    code = ("from jetbot_rt.service.runtime_dir import private_dir\n"
            "print(private_dir())\n")
    with tmp_names(victim):
        target = shared_dir(victim)
        try:
            assert as_user(hostile, "import os, sys\nos.symlink(sys.argv[1], sys.argv[2])\n",
                           str(target), f"/tmp/jetbot-rt-{victim}").returncode == 0
            first = as_user(victim, code, modules=("jetbot_rt.service.runtime_dir", "tempfile"))
            again = as_user(victim, code, modules=("jetbot_rt.service.runtime_dir", "tempfile"))
            assert first.returncode == 0, first.stderr
            chosen = Path(first.stdout.strip())
            assert chosen.name.startswith(f"jetbot-rt-{victim}.") and chosen.parent == Path("/tmp")
            assert again.stdout == first.stdout
            assert list(target.iterdir()) == []
        finally:
            shutil.rmtree(target)


# ---- root never looks in /tmp --------------------------------------------------------------

ROOT_IN_A_NAMESPACE = """
import os, subprocess, sys, time
import jetbot_rt
# the interpreter or the code it imports may lie under /tmp (benchmarks/mutation.py's workers
# are copies there): their top directory is bound back into this namespace's own /tmp
kept = sorted({p.split("/")[2] for p in (sys.executable, sys.prefix, jetbot_rt.__file__)
               if p.startswith("/tmp/") and p.count("/") > 2})
def mount(*args):
    subprocess.run(["mount", *args], check=True)
mount("-t", "tmpfs", "tmpfs", "/run")  # this mount namespace's own: nothing of the machine's
if kept:
    os.mkdir("/run/machine-tmp")
    mount("--bind", "/tmp", "/run/machine-tmp")
mount("-t", "tmpfs", "tmpfs", "/tmp")
for name in kept:
    os.mkdir("/tmp/" + name)
    mount("--bind", "/run/machine-tmp/" + name, "/tmp/" + name)
if kept:
    subprocess.run(["umount", "/run/machine-tmp"], check=True)
    os.rmdir("/run/machine-tmp")
os.mkdir("/tmp/jetbot-rt-0", 0o777)
os.chmod("/tmp/jetbot-rt-0", 0o777)
os.chown("/tmp/jetbot-rt-0", int(sys.argv[1]), int(sys.argv[1]))
listener = subprocess.Popen([sys.executable, "-c", sys.argv[2], "-",
                             *[f"/tmp/jetbot-rt-0/control-{n}.sock" for n in range(40)]],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
assert listener.stdout.readline().strip() == "ready"
from jetbot_rt.hal.i2c import I2CBus
from jetbot_rt.hal.motors import WaveshareDrive
from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator
chip = PCA9685Emulator(0x60, state_file="/tmp/chip")
WaveshareDrive(I2CBus(chip, 1), 0x60, 1600.0).write(0.6, 0.6)
env = dict(os.environ)  # without a runtime directory (the test's caller removed them)
t0 = time.monotonic()
stop = subprocess.run([sys.executable, "-m", "jetbot_rt.cli", "stop", "--board-emulator",
                       "/tmp/chip"], capture_output=True, text=True, env=env, timeout=60)
elapsed = time.monotonic() - t0
from jetbot_rt.service.stop_socket import ControlServer
server = ControlServer(lambda _reason: None)
server.start()
print("server", server.path, oct(os.stat(server.path.parent).st_mode & 0o7777))
server.close()
out, _ = listener.communicate("")
print("accepted", out.split()[0])
print("exit", stop.returncode, "off", chip.refresh().all_off(), "elapsed", round(elapsed, 3))
print(stop.stdout + stop.stderr)
"""


def _private_mounts() -> bool:
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(not _private_mounts(), reason="needs root and a private mount namespace "
                    "(unshare -m) to give root a /run and /tmp of its own")
def test_root_never_uses_the_tmp_fallback() -> None:
    """Root without a runtime directory in the environment (sudo, a root login, cron) uses
    /run/jetbot-rt, never /tmp: another user's /tmp/jetbot-rt-0 with 40 silent sockets is
    not even looked at. In a mount namespace of its own, so the machine's /run (a real
    service's socket) is never touched."""
    hostile = unused_uid()
    result = subprocess.run(["unshare", "-m", sys.executable, "-c", ROOT_IN_A_NAMESPACE,
                             str(hostile), LISTENER], capture_output=True, text=True,
                            timeout=120, cwd="/", env=user_env())
    assert result.returncode == 0, result.stdout + result.stderr
    lines = result.stdout.splitlines()
    assert re.fullmatch(r"server /run/jetbot-rt/control-\d+\.sock 0o700", lines[0]), lines
    assert lines[1] == "accepted 0", lines
    assert lines[2].startswith("exit 0 off True"), result.stdout
    assert "/tmp/jetbot-rt-0" not in result.stdout


# ---- the emulator's state file keeps its owner ---------------------------------------------


@needs_root
def test_a_stop_as_root_leaves_the_emulator_file_to_its_user(tmp_path: Path) -> None:
    """The service's user made the board's state file (mode 0600); a ``jetbot-rt stop`` as
    root writes it; the service's user can still drive it afterwards (it could not when the
    emulator rewrote the file as root)."""
    service = unused_uid()
    work = shared_dir(service)
    chip_file = work / "chip.json"
    drive = ("import os, sys\nos.umask(0o077)\n"
             "from jetbot_rt.hal.i2c import I2CBus\n"
             "from jetbot_rt.hal.motors import WaveshareDrive\n"
             "from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator\n"
             "WaveshareDrive(I2CBus(PCA9685Emulator(0x60, state_file=sys.argv[1]), 1), 0x60,"
             " 1600.0).write(0.5, 0.5)\n")
    modules = ("jetbot_rt.hal.motors", "jetbot_rt.testing.pca9685_emulator", "smbus2")
    try:
        first = as_user(service, drive, str(chip_file), modules=modules)
        assert first.returncode == 0, first.stderr
        before = os.stat(chip_file)
        assert (before.st_uid, stat.S_IMODE(before.st_mode)) == (service, 0o600)
        stop = subprocess.run([sys.executable, "-m", "jetbot_rt.cli", "stop",
                               "--board-emulator", str(chip_file)], capture_output=True,
                              text=True, timeout=HANG_S)
        assert stop.returncode == 0, stop.stdout + stop.stderr
        after = os.stat(chip_file)
        again = as_user(service, drive, str(chip_file), modules=modules)
        chip = PCA9685Emulator(state_file=chip_file)
    finally:
        shutil.rmtree(work)
    assert (after.st_uid, after.st_gid, stat.S_IMODE(after.st_mode)) == \
        (before.st_uid, before.st_gid, 0o600)
    assert again.returncode == 0, again.stderr  # set the board up again and drove
    assert chip.channel(1).duty == pytest.approx(0.5, abs=1e-3)


@needs_root
def test_a_state_file_root_creates_belongs_to_its_directorys_owner() -> None:
    service = unused_uid()
    work = shared_dir(service)
    try:
        PCA9685Emulator(0x60, state_file=work / "chip.json")
        owner = os.stat(work / "chip.json").st_uid
    finally:
        shutil.rmtree(work)
    assert owner == service


def test_the_listener_socket_helper_really_accepts(tmp_path: Path) -> None:
    """The silent sockets above accept (a connection is made, nothing comes back), so a stop
    that asked them would wait: the cases test what they claim."""
    listener = Listener([tmp_path / "s.sock"])
    try:
        client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        client.settimeout(0.3)
        client.connect(str(tmp_path / "s.sock"))
        client.sendall(b"stop\n")
        with pytest.raises(TimeoutError):
            client.recv(64)
        client.close()
        assert listener.finish() == (1, 0)
    finally:
        listener.kill()


# ---- a record directory another user planted ------------------------------------------------


@needs_root
@needs_gst
@pytest.mark.parametrize("planted", ["link", "their directory", "their link as a parent"])
def test_a_record_directory_another_user_planted_is_refused_before_the_board_is_touched(
        tmp_path: Path, planted: str) -> None:
    """H owns a shared directory and plants ``rec`` there: a link to a directory only root can
    write, an empty directory of H's own, or a link as its parent. Root's ``run --record``
    refuses in one line (exit 2) before it opens the board, and writes nothing anywhere."""
    hostile = unused_uid()
    theirs = shared_dir(hostile)
    victim_dir = tmp_path / "rootonly"
    victim_dir.mkdir(mode=0o700)
    plant = {"link": "os.symlink(sys.argv[2], sys.argv[1] + '/rec')",
             "their directory": "os.mkdir(sys.argv[1] + '/rec')",
             "their link as a parent": "os.symlink(sys.argv[2], sys.argv[1] + '/sub')"}[planted]
    record = theirs / ("sub/rec" if planted == "their link as a parent" else "rec")
    config = tmp_path / "dry.toml"
    config.write_text(real_config(live_camera("h25record")))
    (tmp_path / "rt").mkdir(mode=0o700)
    try:
        assert as_user(hostile, f"import os, sys\n{plant}\n", str(theirs),
                       str(victim_dir)).returncode == 0
        result = subprocess.run(
            [sys.executable, "-c", CLI, "run", "--backend", "real", "--config", str(config),
             "--board-emulator", str(tmp_path / "chip.json"), "--duration", "1",
             "--record", str(record)], capture_output=True, text=True, timeout=60, cwd="/",
            env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "rt")))
        left = sorted(p.name for p in theirs.iterdir())
    finally:
        shutil.rmtree(theirs)
    assert result.returncode == 2, result.stdout + result.stderr
    (line,) = result.stderr.splitlines()
    expected = {"link": "is a symbolic link", "their directory": f"belongs to uid {hostile}",
                "their link as a parent": f"is a symbolic link of uid {hostile}"}[planted]
    assert f"record directory {record}" in line and expected in line, line
    assert list(victim_dir.iterdir()) == []
    assert left == ["rec" if planted != "their link as a parent" else "sub"]
    assert not (tmp_path / "chip.json").exists()  # the board was never opened


# ---- the emulator's owner lock: no more open than its state file ------------------------------

TRY_LOCK = ("import fcntl, os, sys\n"
            "try:\n"
            "    fd = os.open(sys.argv[1], os.O_RDONLY | os.O_NOFOLLOW)\n"
            "    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)\n"
            "except OSError as exc:\n"
            "    sys.exit(exc.strerror)\n")


@needs_root
def test_the_owner_lock_root_creates_is_the_state_files_owners_and_closed_to_others() -> None:
    """The service's user made the state file (0600); root (a ``check``, a ``run``) creates
    the ``.owner`` lock beside it: the service's, mode 0600, so another user cannot open it
    to take the lock (it was 0666: any user could refuse every run and fail every stop)."""
    service, hostile = unused_uid(), unused_uid()
    work = shared_dir(service)
    os.chmod(work, 0o1777)  # as /tmp
    chip_file = work / "chip.json"
    try:
        assert as_user(service, "import os, sys\nos.umask(0o077)\n"
                       "from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator\n"
                       "PCA9685Emulator(0x60, state_file=sys.argv[1])\n", str(chip_file),
                       modules=("jetbot_rt.testing.pca9685_emulator",)).returncode == 0
        from jetbot_rt.hal.ownership import BoardLock

        BoardLock.acquire(1, str(chip_file)).release()
        st = os.lstat(f"{chip_file}.owner")
        taken = as_user(hostile, TRY_LOCK, f"{chip_file}.owner", modules=("fcntl",))
        mine = as_user(service, TRY_LOCK, f"{chip_file}.owner", modules=("fcntl",))
    finally:
        shutil.rmtree(work)
    assert (st.st_uid, stat.S_IMODE(st.st_mode)) == (service, 0o600)
    assert taken.returncode == 1 and "Permission denied" in taken.stderr
    assert mine.returncode == 0, mine.stderr


@needs_root
@needs_gst
@pytest.mark.parametrize("planted", ["their file, locked", "a link", "ours, open to all"])
def test_an_owner_lock_file_another_user_planted_refuses_run_and_leaves_stop_confirmed(
        tmp_path: Path, planted: str) -> None:
    """In a directory anyone writes (the documented dry run's /tmp), H makes ``chip.json.owner``
    first and holds a lock on it, or plants a link there. Root's ``run`` refuses in one line
    (exit 2) before it opens the board; root's ``stop`` puts the board off and confirms it
    (it said "NOT confirmed": H's lock looked like a runtime that would not end)."""
    hostile = unused_uid()
    work = shared_dir(0)
    os.chmod(work, 0o1777)
    chip_file, lock_file = work / "chip.json", work / "chip.json.owner"
    hold = ("import fcntl, os, sys, time\n"
            "fd = os.open(sys.argv[1], os.O_RDONLY | os.O_CREAT, 0o666)\n"
            "fcntl.flock(fd, fcntl.LOCK_EX)\nprint('ready', flush=True)\nsys.stdin.read()\n")
    holder = None
    if planted == "ours, open to all":  # what the earlier code made: root's, 0666
        os.close(os.open(lock_file, os.O_CREAT | os.O_RDONLY, 0o600))
        os.chmod(lock_file, 0o666)
    elif planted == "a link":
        assert as_user(hostile, "import os, sys\nos.symlink('/etc/passwd', sys.argv[1])\n",
                       str(lock_file)).returncode == 0
    else:
        holder = subprocess.Popen(command(hostile, hold, str(lock_file), modules=("fcntl",)),
                                  cwd="/", text=True,
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        assert holder.stdout is not None and holder.stdout.readline().strip() == "ready"
    env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path))
    try:
        config = tmp_path / "dry.toml"
        config.write_text(real_config(live_camera("h25owner")))
        run = subprocess.run([sys.executable, "-c", CLI, "run", "--backend", "real", "--config",
                              str(config), "--board-emulator", str(chip_file), "--duration",
                              "1"], capture_output=True, text=True, timeout=60, cwd="/",
                             env=env)
        mode = stat.S_IMODE(os.lstat(lock_file).st_mode)
        stop = subprocess.run([sys.executable, "-c", CLI, "stop", "--board-emulator",
                               str(chip_file)], capture_output=True, text=True,
                              timeout=HANG_S, cwd="/", env=env)
        chip = PCA9685Emulator(state_file=chip_file)
    finally:
        if holder is not None:
            holder.communicate("", timeout=30)
        shutil.rmtree(work)
    assert stop.returncode == 0, stop.stdout + stop.stderr
    assert chip.all_off() and chip.sleeping
    if planted == "ours, open to all":  # closed to others, then ours to use
        assert mode & 0o007 == 0 and run.returncode == 0, (oct(mode), run.stdout + run.stderr)
        return
    assert run.returncode == 2, run.stdout + run.stderr
    (line,) = run.stderr.splitlines()
    expected = "a symbolic link" if planted == "a link" else f"owned by uid {hostile}"
    assert f"{lock_file} is {expected}" in line, line


@needs_root
def test_a_user_trusts_a_board_record_root_left_in_the_users_own_directory() -> None:
    """A run under sudo with the user's ``JETBOT_RT_RUNTIME_DIR`` leaves root's board record
    in the user's directory: the user's ``stop`` trusts it (root's files are trusted
    wherever they are); the same file owned by a third user it does not."""
    import json
    import tempfile

    user, third = unused_uid(), unused_uid()
    directory = Path(tempfile.mkdtemp(prefix="hostile-record-", dir="/tmp"))
    try:
        record = directory / "board.json"
        record.write_text(json.dumps({"i2c_bus": 1, "address": 0x60, "pid": os.getpid(),
                                      "emulator": None}))
        os.chmod(record, 0o644)
        os.chown(directory, user, user)
        code = ("from jetbot_rt.service.runtime_dir import search\n"
                "found = search()\n"
                "print(json.dumps([[str(p), uid] for p, uid in found.records]))\n")
        env = dict(user_env(), JETBOT_RT_RUNTIME_DIR=str(directory))
        result = as_user(user, code, modules=("jetbot_rt.service.runtime_dir",), env=env)
        assert result.returncode == 0, result.stderr
        assert json.loads(result.stdout) == [[str(record), user]]
        os.chown(record, third, third)
        result = as_user(user, code, modules=("jetbot_rt.service.runtime_dir",), env=env)
        assert json.loads(result.stdout) == [], result.stdout
    finally:
        shutil.rmtree(directory, ignore_errors=True)
