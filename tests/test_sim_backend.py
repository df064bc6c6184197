"""The ``sim`` backend through the HAL factory, on a real PyBullet world."""

from __future__ import annotations

import numpy as np
import pytest

from jetbot_rt.config.sections import Config
from jetbot_rt.errors import Fault, UsageError
from jetbot_rt.hal.registry import BackendOptions, make_backend

TICK = 1 / 30


def sim_backend(config: Config | None = None, options: BackendOptions | None = None):
    robot = make_backend("sim", config or Config(), options or BackendOptions())
    robot.connect()
    return robot


@pytest.fixture
def backend():
    b = sim_backend()
    yield b
    b.disconnect()


def advance(backend, seconds: float) -> list:
    """Advance tick by tick; the frame read after each tick."""
    return [tick[0] for tick in advance_timed(backend, seconds)]


def advance_timed(backend, seconds: float) -> list:
    """Advance tick by tick; (frame read after the tick, simulated time) per tick."""
    ticks = []
    for _ in range(round(seconds / TICK)):
        backend.step(TICK)
        ticks.append((backend.camera.read(), backend.state()["sim_time"]))
    return ticks


def test_camera_renders_at_start_and_on_advance_only(backend):
    assert backend.camera.read() is None  # nothing before start
    backend.camera.start()
    first = backend.camera.read()
    assert first.image.shape == (224, 224, 3) and first.image.dtype == np.uint8
    assert backend.camera.read() is first  # reading does not render
    backend.step(TICK)
    second = backend.camera.read()
    assert second.index == first.index + 1
    assert second.t_capture >= first.t_capture
    backend.camera.stop()
    assert backend.camera.read() is None


def test_drive_moves_the_robot_and_stop_brakes_it(backend):
    backend.camera.start()
    backend.drive.write(0.1, 0.1)
    advance(backend, 2.0)
    x = backend.state()["pose"][0]
    assert 0.08 < x + 0.6 < 0.14  # 0.06 m/s
    backend.drive.stop()
    advance(backend, 0.5)  # the motor lag and the contact settle
    settled = backend.state()["pose"][0]
    advance(backend, 1.0)
    assert backend.state()["pose"][0] == pytest.approx(settled, abs=1e-3)


def test_telemetry_reports_pose_and_sim_time(backend):
    backend.camera.start()
    advance(backend, 1.0)
    extra = backend.state()
    assert set(extra) == {"pose", "sim_time", "goal_distance", "goal"}
    assert extra["sim_time"] == pytest.approx(1.0)
    assert extra["pose"] == pytest.approx([-0.6, 0.0, 0.0], abs=1e-3)
    assert extra["goal"] == pytest.approx([0.3, 0.0], abs=0.01)  # 0.9 m ahead of the start
    assert extra["goal_distance"] == pytest.approx(0.9, abs=0.01)


def test_non_finite_duty_is_a_fault(backend):
    with pytest.raises(Fault):
        backend.drive.write(float("nan"), 0.0)


def test_camera_stall_keeps_returning_the_last_frame():
    config = Config()
    config.sim.camera_stall_after = 0.5
    backend = sim_backend(config)
    try:
        backend.camera.start()
        backend.drive.write(0.3, 0.3)  # the view changes while the camera is stalled
        frames = advance(backend, 1.0)
    finally:
        backend.disconnect()
    indices = [f.index for f in frames]
    assert indices[:15] == list(range(2, 17))  # one new frame per tick up to t = 0.5 s
    assert all(f is frames[14] for f in frames[15:])  # then the same frame: it goes stale


def test_blackout_renders_black_frames_in_its_window():
    config = Config()
    config.sim.blackout = [0.2, 0.4]
    backend = sim_backend(config)
    try:
        backend.camera.start()
        ticks = advance_timed(backend, 0.6)
    finally:
        backend.disconnect()
    black = [sim_time for frame, sim_time in ticks if not frame.image.any()]
    assert black == [t for _, t in ticks if 0.2 <= t <= 0.4]
    assert len(black) == 7  # 0.2, 0.233, ..., 0.4
    assert len({frame.index for frame, _ in ticks}) == len(ticks)  # new frames, just black


def test_frame_size_option_sets_the_render_size():
    backend = sim_backend(options=BackendOptions(frame_size=(160, 120)))
    try:
        backend.camera.start()
        assert backend.camera.read().image.shape == (120, 160, 3)
    finally:
        backend.disconnect()


def test_frames_show_the_red_block_straight_ahead(backend):
    backend.camera.start()
    image = backend.camera.read().image.astype(int)
    red = (image[:, :, 0] > 100) & (image[:, :, 0] > 2 * image[:, :, 1]) & (
        image[:, :, 0] > 2 * image[:, :, 2]
    )
    assert red.sum() > 20
    assert abs(np.nonzero(red)[1].mean() - 111.5) < 6


def test_gui_without_a_display_is_a_usage_error(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(UsageError, match="display"):
        sim_backend(options=BackendOptions(gui=True))


def test_the_robot_lifecycle_as_a_context_manager():
    """No drive before connect; inside ``with`` it drives and its time steps; on the way out
    the motors are at zero and the camera is stopped; ``stats`` still answers afterwards."""
    robot = make_backend("sim", Config(), BackendOptions(frame_size=(64, 48)))
    with pytest.raises(RuntimeError, match="not connected"):
        robot.drive  # noqa: B018
    with robot:
        robot.camera.start()
        robot.drive.write(0.3, 0.3)
        for _ in range(30):
            robot.step(TICK)
        assert robot.state()["sim_time"] == pytest.approx(1.0)
        assert robot.camera.read().image.shape == (48, 64, 3)
        world = robot._world
        assert world.duty == (0.3, 0.3)
    assert world.duty == (0.0, 0.0)
    assert robot.camera.read() is None
    assert robot.stats()["travelled_m"] > 0.05
