"""Domain randomization: per-episode draws of the [sim] knobs from the env's seeded RNG."""

from __future__ import annotations

import numpy as np
import pytest

from jetbot_rt.config.sections import from_dict
from jetbot_rt.errors import UsageError

pytest.importorskip("pybullet")

from jetbot_rt.sim.config import randomized_knobs
from jetbot_rt.sim.look_draws import LOOK_KEYS
from jetbot_rt.sim.randomize import DRAWN, params, sample, sim_toml
from jetbot_rt.train.env import JetbotEnv

# max_speed above the default dead-band range (0..0.3); the appearance families have their own
# tests (test_appearance_families.py)
CONFIG = {"actions": {"max_speed": 0.4}, "randomize": {"appearance": False}}


@pytest.fixture(scope="module")
def env():
    environment = JetbotEnv("forward", from_dict(CONFIG), randomize=True)
    yield environment
    environment.close()


def episode(env: JetbotEnv, seed: int, steps: int = 4):
    obs, info = env.reset(seed=seed)
    frames = [obs] + [env.step(np.array([0.8, 0.5]))[0] for _ in range(steps)]
    return info, np.array(frames), env.world.robot_pose()


def test_same_seed_same_draw_and_frames_different_seed_different(env):
    info_a, frames_a, pose_a = episode(env, 7)
    episode(env, 8)  # the env's state in between does not leak into the next seeded episode
    info_b, frames_b, pose_b = episode(env, 7)
    assert info_a["sim_params"] == info_b["sim_params"] == env.sim_params
    info_c, frames_c, _ = episode(env, 9)
    assert set(info_a["sim_params"]) == set(DRAWN)
    assert np.array_equal(frames_a, frames_b) and pose_a == pose_b
    # floor_texture: a choice of two may repeat; the appearance families are off here
    looks_off = set(LOOK_KEYS) - {name for name, _ in randomized_knobs()}
    continuous = [k for k in DRAWN if k != "floor_texture" and k not in looks_off]
    differ = [k for k in continuous if info_a["sim_params"][k] != info_c["sim_params"][k]]
    assert differ == continuous  # every knob is drawn again
    assert not np.array_equal(frames_a[0], frames_c[0])


def test_draws_lie_in_their_ranges_and_cover_them():
    config = from_dict(CONFIG)
    rng = np.random.default_rng(0)
    draws = [sample(config.sim, config.randomize, rng) for _ in range(300)]
    gains = np.array([d.wheel_gain for d in draws])
    assert gains.min() >= 0.8 and gains.max() <= 1.2
    assert gains.min() < 0.82 and gains.max() > 1.18  # each wheel apart, over the range
    assert np.corrcoef(gains.T)[0, 1] < 0.3
    for key in ("latency", "camera_latency", "deadband"):
        values = np.array([getattr(d, key) for d in draws])
        low, high = getattr(config.randomize, key)
        assert low <= values.min() < low + 0.05 * (high - low)
        assert high - 0.05 * (high - low) < values.max() <= high
    pitch = np.array([d.camera_pitch_deg for d in draws])
    assert 16.0 <= pitch.min() < 16.5 and 23.5 < pitch.max() <= 24.0  # 20 deg * (0.8..1.2)
    assert all(d.block_color[0] > 3 * max(d.block_color[1:]) for d in draws)  # still red
    plain = sum(d.floor_texture == "plain" for d in draws) / len(draws)
    assert 0.2 < plain < 0.4  # floor_plain = 0.3 of them; the rest keep [sim]'s checker
    assert {d.floor_texture for d in draws} == {"plain", "checker"}
    plain_floors = np.array([d.floor_color for d in draws if d.floor_texture == "plain"])
    assert plain_floors.min() < 0.15 and plain_floors.max() > 0.8  # dark and light, any hue
    assert all(f[0] <= max(f[1:]) / 0.7 + 1e-6 for f in plain_floors)  # never a red floor
    light = np.array([d.light_intensity for d in draws])
    assert 0.5 <= light.min() < 0.55 and 1.25 < light.max() <= 1.3


def test_a_draw_replays_as_a_sim_table():
    config = from_dict(CONFIG)
    draw = sample(config.sim, config.randomize, np.random.default_rng(3))
    import tomllib

    assert from_dict(tomllib.loads(sim_toml(draw))).sim == draw


def test_randomization_is_off_unless_asked_and_keeps_the_start_poses():
    plain = JetbotEnv("forward")
    try:
        _, info = plain.reset(seed=5)
        assert not plain.randomize
        assert info["sim_params"]["wheel_gain"] == [1.0, 1.0]
        assert info["sim_params"]["latency"] == 0.0
        start = plain.world.robot_pose()
    finally:
        plain.close()
    randomized = JetbotEnv("forward", from_dict({**CONFIG, "randomize": {"enabled": True}}))
    try:
        assert randomized.randomize
        randomized.reset(seed=5)
        assert randomized.world.robot_pose() == pytest.approx(start, abs=1e-9)
    finally:
        randomized.close()


def test_max_speed_must_lie_above_the_deadband_it_trains_with():
    with pytest.raises(UsageError, match="deadband"):
        JetbotEnv("forward", randomize=True)  # max_speed 0.1, dead-band up to 0.3
    narrow = from_dict({"randomize": {"deadband": [0.0, 0.05]}})
    JetbotEnv("forward", narrow, randomize=True).close()


def test_the_default_config_file_shows_the_defaults():
    from importlib import resources

    from jetbot_rt.config.sections import Config, load_config

    shipped = load_config(str(resources.files("jetbot_rt") / "data" / "default-config.toml"))
    assert shipped.sim == Config().sim and shipped.randomize == Config().randomize


def test_the_sim_backend_draws_once_from_its_seed_when_enabled():
    from jetbot_rt.hal.registry import BackendOptions, make_backend

    def first_frame(data: dict) -> np.ndarray:
        backend = make_backend("sim", from_dict(data), BackendOptions(frame_size=(64, 64)))
        try:
            backend.camera.start()
            return backend.camera.read().image.copy()
        finally:
            backend.disconnect()

    plain = first_frame({})
    drawn = first_frame({"randomize": {"enabled": True}, "sim": {"seed": 11}})
    again = first_frame({"randomize": {"enabled": True}, "sim": {"seed": 11}})
    other = first_frame({"randomize": {"enabled": True}, "sim": {"seed": 12}})
    assert np.array_equal(drawn, again)
    assert not np.array_equal(drawn, plain) and not np.array_equal(drawn, other)


def test_the_reported_draw_tells_appearance_families_apart():
    config = from_dict({"randomize": {"appearance": True}})
    rng = np.random.default_rng(0)
    draws = [params(sample(config.sim, config.randomize, rng)) for _ in range(2)]
    assert set(LOOK_KEYS) <= set(draws[0])
    assert draws[0]["look_seed"] != draws[1]["look_seed"]


def test_a_calibrated_lift_follows_each_episodes_drawn_deadband():
    plain = JetbotEnv("seek", from_dict({}), randomize=True)
    calibrated = JetbotEnv("seek", from_dict({"randomize": {"deadband_lift": [-0.05, 0.05]}}),
                           randomize=True)
    try:
        for seed in (3, 4, 5, 6):
            _, without = plain.reset(seed=seed)
            _, drawn = calibrated.reset(seed=seed)
            lift = drawn["sim_params"].pop("deadband_lift")
            assert drawn["sim_params"] == without["sim_params"]  # the same world, lifted
            deadband = drawn["sim_params"]["deadband"]
            assert max(deadband - 0.05, 0.0) <= lift <= deadband + 0.05
            assert calibrated.pipeline.deadband == lift and plain.pipeline.deadband == 0.0
            assert "deadband_lift" not in without["sim_params"]
        calibrated.randomize = False  # as a vector env's set_attr does: no lift left behind
        _, fixed = calibrated.reset(seed=3)
        assert calibrated.pipeline.deadband == 0.0 and "deadband_lift" not in fixed["sim_params"]
    finally:
        plain.close()
        calibrated.close()
