"""Fault matrix, exit paths that hang (class 5): telemetry to a FIFO whose reader
stalls or is absent, a stop request or signal during warm-up, idle clients on the control
socket. Each ends with the board all off within the stated bound, the documented exit code,
one line at most on stderr, no traceback and no camera child left (docs/SAFETY.md).
"""

from __future__ import annotations

import fcntl
import os
import signal
import socket
import struct
import termios
import time
import uuid
from pathlib import Path

import policy_models
import pytest
from fault_helpers import (
    MU,
    SwitchableCamera,
    assert_no_gst_left,
    live_camera,
    needs_gst,
    real_config,
    record_figures,
)
from runner import RuntimeProcess, processes_with, wait_for

from jetbot_rt.service.stop_socket import request_stop

pytestmark = needs_gst

EXIT_BOUND_S = 1.0
"""Stated bound: stop sent -> process gone (the issue's 1 s), also board off."""
HANG_BOUND_S = 5.0
"""Where what the test tells apart is a hang (a warm-up that waits out warmup_timeout, 300 s;
an exit that waits for a reader that never reads), the bound is far from any scheduler delay:
the measured times (JETBOT_RT_FAULT_FIGURES, docs/SAFETY.md) show the 1 s target is met."""
F_SETPIPE_SZ = 1031

PATIENT = "[loop]\nwatchdog_timeout = 1.0\nmax_frame_age = 1.0\n"
"""These cases are about signals and stop requests, not the watchdog or stale frames: generous
thresholds keep a loaded CI host (a loaded 2-core VM) from ending the run first."""


def control_socket(rt: RuntimeProcess) -> Path:
    """The runtime's own control socket (one per runtime, named by its pid)."""
    return rt.root / "run" / f"control-{rt.pid}.sock"


def stalled_fifo(tmp_path: Path) -> tuple[Path, int]:
    """A FIFO with a reader that never reads, its buffer shrunk to one page (fills in <1 s)."""
    path = tmp_path / "telemetry.fifo"
    os.mkfifo(path)
    reader = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    fcntl.fcntl(reader, F_SETPIPE_SZ, 4096)
    return path, reader


def pipe_full(reader: int) -> bool:
    """No room left for another record (each is over 200 bytes; a write of one waits for room
    for all of it): the writer is blocked for good."""
    held = struct.unpack("i", fcntl.ioctl(reader, termios.FIONREAD, b"\0" * 4))[0]
    return held > 4096 - 200


def summary_lines(stdout: str) -> dict[str, str]:
    lines = {}
    for line in stdout.splitlines()[1:]:
        key, _, value = line.strip().partition("  ")
        lines[key] = value.strip()
    return lines


# SIGINT takes SIGTERM's path (one handler; test_fault_signals.py checks each is caught).
@pytest.mark.parametrize("how", ["SIGTERM", "stop-command", "policy-hangs"])
def test_stalled_telemetry_reader_blocks_neither_the_loop_nor_the_exit(tmp_path: Path,
                                                                       how: str) -> None:
    mark = f"fh{uuid.uuid4().hex[:12]}"
    fifo, reader = stalled_fifo(tmp_path)
    make = policy_models.hang_when_dark if how == "policy-hangs" else policy_models.constant
    policy = make(tmp_path / "policy.onnx", MU)
    # policy-hangs drives until the FIFO is full, then the lens goes black
    switchable = SwitchableCamera(tmp_path, mark) if how == "policy-hangs" else None
    camera = switchable.pipeline if switchable else live_camera(mark)
    patient = "" if how == "policy-hangs" else PATIENT  # there the watchdog is the point
    rt = RuntimeProcess(tmp_path, "real", policy, config=real_config(camera) + patient,
                        telemetry=fifo)
    try:
        rt.start()
        assert wait_for(lambda: not rt.board_off(), 60, interval=0.02) is not None
        assert wait_for(lambda: pipe_full(reader), 60, interval=0.02) is not None
        assert rt.process.poll() is None
        t0 = time.monotonic()
        if how == "SIGTERM":
            os.kill(rt.pid, signal.SIGTERM)
        elif how == "SIGINT":
            os.kill(rt.pid, signal.SIGINT)
        elif how == "stop-command":
            assert request_stop(control_socket(rt)).acknowledged
        else:
            assert not rt.board_off(), "still driving with the reader stalled"
            switchable.show_black()
        t_off = wait_for(rt.board_off, EXIT_BOUND_S + (5 if how == "policy-hangs" else 0))
        assert t_off is not None
        out, err = rt.finish_raw(EXIT_BOUND_S + 5)
        t_exit = time.monotonic()
    finally:
        rt.kill()
        os.close(reader)
    code = 3 if how == "policy-hangs" else 0
    assert rt.process.returncode == code, out + err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and "telemetry" in err, err
    summary = summary_lines(out)
    assert int(summary["telemetry"].split()[0]) > 0, out  # the dropped records are counted
    if how != "policy-hangs":  # the exit waits <= 0.5 s for the writer by design, then leaves
        assert t_exit - t0 < HANG_BOUND_S, f"exit took {t_exit - t0:.2f} s"
    assert rt.board_off()
    assert_no_gst_left(mark)
    record_figures(f"telemetry-fifo-stalled-{how}-real", exit_code=code,
                   inject_to_board_off_s=round(t_off - t0, 4),
                   inject_to_exit_s=round(t_exit - t0, 4))


@pytest.mark.parametrize("where", ["config", "flag"])
def test_telemetry_fifo_without_a_reader_is_refused_at_once(tmp_path: Path, where: str) -> None:
    mark = f"fh{uuid.uuid4().hex[:12]}"
    fifo = tmp_path / "telemetry.fifo"
    os.mkfifo(fifo)
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    config = real_config(live_camera(mark))
    if where == "config":
        config += f'[telemetry]\npath = "{fifo}"\n'
    rt = RuntimeProcess(tmp_path, "real", policy, config=config,
                        telemetry=fifo if where == "flag" else tmp_path / "unused.jsonl")
    if where == "config":
        rt.args = [a for a in rt.args if a not in ("--telemetry", str(rt.telemetry))]
    try:
        rt.start()
        out, err = rt.finish_raw(20)
    finally:
        rt.kill()
    assert rt.process.returncode == 2, out + err
    (line,) = err.strip().splitlines()
    assert "FIFO with no reader" in line and str(fifo) in line
    assert rt.board_off()
    assert_no_gst_left(mark)


def black_camera(mark: str) -> str:
    return f"videotestsrc name={mark} pattern=black is-live=true"


@pytest.mark.parametrize(("how", "delay"), [  # SIGINT, SIGQUIT: SIGTERM's handler
    ("SIGTERM", 0.3), ("stop-command", 0.5), ("SIGTSTP", 0.4),
])
def test_stop_during_warm_up_ends_the_run(tmp_path: Path, how: str,
                                                     delay: float) -> None:
    """The policy's first inference never returns (as a TensorRT build that takes minutes):
    a stop request or a signal ends the run at once, with the default warmup_timeout (300 s)."""
    mark = f"fh{uuid.uuid4().hex[:12]}"
    policy = policy_models.hang_when_dark(tmp_path / "policy.onnx", MU)
    rt = RuntimeProcess(tmp_path, "real", policy,
                        config=real_config(black_camera(mark)) + PATIENT)
    try:
        rt.start()
        # warming up: the camera child delivers, the telemetry has no tick
        assert wait_for(lambda: rt.process.poll() is not None or
                        bool(processes_with(mark)), 60, interval=0.02) is not None
        time.sleep(1.0 + delay)  # the camera's first frame is in, the inference hangs
        assert rt.process.poll() is None
        t0 = time.monotonic()
        if how == "stop-command":
            assert request_stop(control_socket(rt)).acknowledged
        else:
            os.kill(rt.pid, getattr(signal, how))
            if how == "SIGTSTP":
                assert wait_for(lambda: _state(rt.pid) in ("T", "Z"), 5) is not None
                os.kill(rt.pid, signal.SIGCONT)
        out, err = rt.finish_raw(10)
        t_exit = time.monotonic()
    finally:
        rt.kill()
    assert rt.process.returncode == 0, out + err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 1, err
    if how != "SIGTSTP":
        assert t_exit - t0 < HANG_BOUND_S, f"{t_exit - t0:.2f} s"
    assert rt.board_off()
    assert not [r for r in rt.records() if "event" not in r], "it drove"
    assert_no_gst_left(mark)
    record_figures(f"warm-up-{how}-real", exit_code=0, inject_to_exit_s=round(t_exit - t0, 4))


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"


@pytest.mark.parametrize("clients", ["idle", "half-line", "never-reads"])
def test_control_socket_serves_a_stop_whatever_other_clients_do(tmp_path: Path,
                                                                clients: str) -> None:
    mark = f"fh{uuid.uuid4().hex[:12]}"
    policy = policy_models.constant(tmp_path / "policy.onnx", MU)
    rt = RuntimeProcess(tmp_path, "real", policy,
                        config=real_config(live_camera(mark)) + PATIENT)
    others: list[socket.socket] = []
    try:
        rt.start()
        rt.wait_ticks(10)
        path = control_socket(rt)
        for _ in range(20):  # more than the server keeps: the oldest are dropped
            other = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            other.connect(str(path))
            if clients == "half-line":
                other.sendall(b"st")
            elif clients == "never-reads":
                other.sendall(b"ping\n")
            others.append(other)
        t0 = time.monotonic()
        reply = request_stop(path, timeout=2.0)
        answered = time.monotonic() - t0
        assert reply.acknowledged, reply.unreachable
        assert wait_for(rt.board_off, EXIT_BOUND_S) is not None
        result = rt.finish(20)
    finally:
        for other in others:
            other.close()
        rt.kill()
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.records[-1]["reason"].startswith("jetbot-rt stop from pid")
    assert "Traceback" not in result.stderr and not result.stderr.strip()
    assert answered < 0.5, f"the stop waited {answered:.3f} s behind other clients"
    assert_no_gst_left(mark)
    record_figures(f"control-socket-{clients}-real", exit_code=0,
                   stop_answered_s=round(answered, 4))


def slow_to_load(path: Path, adds: int = 20000) -> Path:
    """A model onnxruntime takes seconds to load (a chain of ``adds`` Add nodes to optimise),
    as a TensorRT engine build at session creation does on a Jetson."""
    import numpy as np
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    nodes = [helper.make_node("ReduceMean", ["obs"], ["m0"], keepdims=0)]
    nodes += [helper.make_node("Add", [f"m{i}", "one"], [f"m{i + 1}"]) for i in range(adds)]
    nodes += [helper.make_node("Mul", [f"m{adds}", "zero"], ["z"]),
              helper.make_node("Add", ["mu_const", "z"], ["mu"])]
    inits = [numpy_helper.from_array(np.array(1.0, np.float32), "one"),
             numpy_helper.from_array(np.array(0.0, np.float32), "zero"),
             numpy_helper.from_array(np.array([list(MU)], np.float32), "mu_const")]
    graph = helper.make_graph(
        nodes, "slow_to_load",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [1, 224, 224, 3])],
        [helper.make_tensor_value_info("mu", TensorProto.FLOAT, [1, 2])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 16)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


@pytest.mark.parametrize("how", ["SIGTERM", "stop-command"])  # SIGINT: SIGTERM's handler
def test_stop_during_the_model_load_ends_the_run_within_1_s(tmp_path: Path, how: str) -> None:
    """The control socket appears right before the model load starts: a stop 0.3 s later
    meets a load that takes seconds (the worker thread is left to the process exit)."""
    mark = f"fh{uuid.uuid4().hex[:12]}"
    policy = slow_to_load(tmp_path / "policy.onnx")
    rt = RuntimeProcess(tmp_path, "real", policy,
                        config=real_config(live_camera(mark)) + PATIENT)
    try:
        rt.start()
        sock = control_socket(rt)
        assert wait_for(lambda: rt.process.poll() is not None or sock.exists(), 60,
                        interval=0.01) is not None
        time.sleep(0.3)
        if rt.process.poll() is not None:
            raise AssertionError("ended before the stop: " + "".join(rt.finish_raw(5)))
        t0 = time.monotonic()
        if how == "stop-command":
            assert request_stop(sock).acknowledged
        else:
            os.kill(rt.pid, getattr(signal, how))
        out, err = rt.finish_raw(10)
        t_exit = time.monotonic()
    finally:
        rt.kill()
    assert rt.process.returncode == 0, out + err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 1, err
    assert t_exit - t0 < EXIT_BOUND_S, f"{t_exit - t0:.2f} s"
    assert not processes_with(mark), "the camera was started"
    assert not [r for r in rt.records() if "event" not in r], "it drove"
    record_figures(f"model-load-{how}-real", exit_code=0, inject_to_exit_s=round(t_exit - t0, 4))
