"""The monitor in a real ``jetbot-rt run --backend real`` (PCA9685 emulator, videotestsrc):
its STOP ends the run as ``jetbot-rt stop`` does, a port in use is bad input before the motors
move; ``install-service`` opens the unit to IP sockets only for a config that serves it."""

from __future__ import annotations

import http.client
import json
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from monitor_helpers import MonitoredRun

from jetbot_rt.cli import main


def get(url: str, path: str, method: str = "GET") -> tuple[int, bytes]:
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=10)
    try:
        conn.request(method, path)
        reply = conn.getresponse()
        return reply.status, reply.read()
    finally:
        conn.close()


@pytest.fixture
def run(tmp_path):
    runs: list[MonitoredRun] = []

    def make(**kwargs) -> MonitoredRun:
        runs.append(MonitoredRun(tmp_path, **kwargs))
        return runs[-1]

    yield make
    for r in runs:
        r.kill()


def test_the_pages_stop_ends_the_run_orderly_with_every_output_off(run) -> None:
    robot = run()
    url = robot.url()
    deadline = time.monotonic() + 30
    state: dict = {}
    while time.monotonic() < deadline:
        state = json.loads(get(url, "/state")[1])
        if state["state"] == "driving" and state["ticks"] > 10:
            break
        time.sleep(0.1)
    assert state["state"] == "driving", state
    assert not robot.chip.refresh().all_off()  # the constant-speed policy drives forward
    assert get(url, "/stop", "POST")[0] == 200
    code, err = robot.finish()
    assert code == 0, err
    assert robot.chip.refresh().all_off()
    assert "stopped      stop from the monitor page (127.0.0.1)" in "".join(robot.out)


def test_a_monitor_port_in_use_is_refused_before_the_motors_move(run, tmp_path) -> None:
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    try:
        robot = run(monitor=f"127.0.0.1:{port}")
        before = robot.chip_file.stat().st_mtime_ns
        code, err = robot.finish()
    finally:
        taken.close()
    assert code == 2
    assert err == f"jetbot-rt run: error: --monitor 127.0.0.1:{port}: cannot listen: the port " \
                  "is in use\n"
    assert robot.chip_file.stat().st_mtime_ns == before  # the board was never opened
    assert robot.chip.refresh().all_off()


@pytest.mark.parametrize("value", ["example.com:80", "70000", "[::1]"])
def test_a_bad_monitor_address_is_one_line_and_exit_2(value, tmp_path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "jetbot_rt.cli", "run", "--backend", "real", "--monitor", value],
        capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.startswith("jetbot-rt run: error: --monitor: [monitor] listen must be")
    assert result.stderr.count("\n") == 1


def test_install_service_allows_ip_sockets_only_when_the_config_serves_the_monitor(
        tmp_path: Path, capsys) -> None:
    config = tmp_path / "etc/jetbot-rt/config.toml"
    unit = tmp_path / "etc/systemd/system/jetbot-rt.service"
    assert main(["install-service", "--root", str(tmp_path), "--user", "root"]) == 0
    assert "RestrictAddressFamilies=AF_UNIX AF_NETLINK\n" in unit.read_text()
    config.write_text('[monitor]\nlisten = "0.0.0.0:8080"\n'
                      'token_file = "/var/lib/jetbot-rt/monitor-token"\n')
    capsys.readouterr()
    assert main(["install-service", "--root", str(tmp_path), "--user", "root", "--force"]) == 0
    assert "RestrictAddressFamilies=AF_UNIX AF_NETLINK AF_INET AF_INET6\n" in unit.read_text()
    assert "allows IP sockets" in capsys.readouterr().out


@pytest.mark.skipif(sys.version_info < (3, 10), reason="the simulator needs Python 3.10 or newer")
def test_a_sim_runs_page_state_has_its_trajectory_and_the_goal(run) -> None:
    sim = run(backend="sim")
    url = sim.url()
    deadline = time.monotonic() + 30
    state: dict = {}
    while time.monotonic() < deadline:
        status, body = get(url, "/state")
        assert status == 200
        state = json.loads(body)
        if len(state.get("trajectory", ())) >= 3:
            break
        time.sleep(0.2)
    assert len(state["trajectory"]) >= 3, state
    # forward's goal: the red block 0.9 m straight ahead of the start (the world's +x)
    gx, gy = state["goal"]
    assert abs(gx - state["trajectory"][0][0] - 0.9) < 0.15 and abs(gy) < 0.15, state
    assert get(url, "/stop", "POST")[0] == 200
    code, err = sim.finish()
    assert code == 0, err
