"""The Gymnasium env on the real PyBullet world: Env contract, registration, seeding, and the
runtime's action pipeline applied to its actions."""

from __future__ import annotations

import subprocess
import sys

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from jetbot_rt.config.sections import from_dict
from jetbot_rt.errors import UsageError
from jetbot_rt.tasks import load_task
from jetbot_rt.tasks.forward import Forward, forward_reward
from jetbot_rt.train.env import POLICY_IMAGE_SIZE, JetbotEnv

pytest.importorskip("pybullet")


@pytest.fixture(scope="module")
def env():
    environment = JetbotEnv("forward")
    yield environment
    environment.close()


def test_check_env_passes_on_the_registered_env():
    made = gymnasium.make("jetbot_rt:JetbotForward-v0")
    try:
        check_env(made.unwrapped, skip_render_check=True)
        assert made.observation_space == gymnasium.spaces.Box(
            0, 255, (POLICY_IMAGE_SIZE, POLICY_IMAGE_SIZE, 3), np.uint8)
        assert made.action_space.shape == (2,)
    finally:
        made.close()


def test_make_works_in_a_fresh_interpreter_and_import_stays_light():
    code = (
        "import sys, gymnasium\n"
        "env = gymnasium.make('jetbot_rt:JetbotForward-v0')\n"
        "obs, info = env.reset(seed=0)\n"
        f"assert obs.shape == ({POLICY_IMAGE_SIZE}, {POLICY_IMAGE_SIZE}, 3)\n"
        "assert obs.dtype.name == 'uint8'\n"
        "env.close()\n"
        "import subprocess\n"
        "light = subprocess.run([sys.executable, '-c', 'import sys, jetbot_rt; "
        "print(sorted(m for m in (\"torch\", \"pybullet\", \"gymnasium\") if m in sys.modules))'],"
        " capture_output=True, text=True, check=True)\n"
        "print(light.stdout.strip())\n"
    )
    assert last_line_printed_by(code) == "[]"


def last_line_printed_by(code: str) -> str:
    """``code`` run in a fresh interpreter, which must exit 0: the last line it printed."""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    return result.stdout.strip().splitlines()[-1]


def test_make_works_when_jetbot_rt_was_imported_before_gymnasium():
    """``make`` imports ``jetbot_rt``, which was imported already (without gymnasium, so
    without registering): the ids are registered when gymnasium itself is imported, also after
    a ``find_spec`` of it (jetbot-train's check of the ``train`` extra) that imported nothing."""
    code = (
        "import importlib.util, sys, jetbot_rt\n"
        "assert 'gymnasium' not in sys.modules\n"
        "assert importlib.util.find_spec('gymnasium') is not None\n"
        "import gymnasium\n"
        "env = gymnasium.make('jetbot_rt:JetbotSeek-v0')\n"
        "print(env.unwrapped.task.name)\n"
        "env.close()\n"
    )
    assert last_line_printed_by(code) == "seek"


def test_same_seed_same_start_and_frames_different_seed_different_start(env):
    obs_a, info_a = env.reset(seed=123)
    frames_a = [env.step(np.array([0.7, 0.3]))[0] for _ in range(3)]
    obs_b, info_b = env.reset(seed=123)
    frames_b = [env.step(np.array([0.7, 0.3]))[0] for _ in range(3)]
    assert np.array_equal(obs_a, obs_b)
    assert np.array_equal(info_a["pose"], info_b["pose"])
    assert all(np.array_equal(a, b) for a, b in zip(frames_a, frames_b, strict=True))
    _, info_c = env.reset(seed=124)
    assert not np.allclose(info_a["pose"], info_c["pose"])
    task = load_task("forward")
    offset = np.abs(np.array(info_a["pose"]) - np.array(task.robot_pose))
    assert offset[0] <= task.start_xy_noise and offset[1] <= task.start_xy_noise
    assert offset[2] <= task.start_yaw_noise


def test_nominal_start_and_seed_task_geometry(env):
    obs, info = env.reset(seed=0, options={"start_noise": False})
    assert np.allclose(info["pose"], (-0.6, 0.0, 0.0))
    assert info["distance"] == pytest.approx(0.9, abs=1e-3)
    # The red block is in view (a 5 cm cube 0.9 m away: 2x4 pixels at 56x56), mid-frame.
    red = (obs[:, :, 0] > 150) & (obs[:, :, 1] < 80) & (obs[:, :, 2] < 80)
    columns = np.nonzero(red.any(axis=0))[0]
    width = obs.shape[1]
    assert red.sum() >= 6 and abs(columns.mean() - (width - 1) / 2) < width / 20


def test_step_goes_through_the_action_pipeline_and_one_control_period(env):
    env.reset(seed=0, options={"start_noise": False})
    _, reward, terminated, truncated, info = env.step(np.array([5.0, -0.5], np.float32))
    assert info["duty"].tolist() == pytest.approx([0.1, -0.05])  # clamp(mu) * max_speed 0.1
    assert info["sim_time"] == pytest.approx(1 / 30, abs=1 / 240)
    assert reward == pytest.approx(forward_reward(info["distance"]))
    assert not terminated and not truncated


def test_config_trim_sign_and_max_speed_reach_the_duties():
    config = from_dict({"actions": {"max_speed": 0.2, "trim": [0.5, 1.0], "sign": [1, -1]}})
    environment = JetbotEnv("forward", config)
    try:
        environment.reset(seed=0)
        info = environment.step(np.array([1.0, 1.0]))[4]
        assert info["duty"].tolist() == pytest.approx([0.1, -0.2])
    finally:
        environment.close()


def test_driving_forward_approaches_the_block_and_reward_grows(env):
    _, info = env.reset(seed=0, options={"start_noise": False})
    rewards = [env.step(np.array([1.0, 1.0]))[1] for _ in range(60)]
    assert env.world.distance_to_block() < info["distance"] - 0.08
    assert rewards[-1] > rewards[0]


def test_episode_ends_only_by_the_time_limit():
    class Short(Forward):
        episode_steps = 5

    environment = JetbotEnv(Short())
    try:
        environment.reset(seed=0)
        flags = [environment.step(np.zeros(2))[2:4] for _ in range(5)]
        assert flags[:4] == [(False, False)] * 4 and flags[4] == (False, True)
    finally:
        environment.close()


def test_unknown_task_is_a_usage_error():
    with pytest.raises(UsageError, match="unknown task 'sideways'"):
        JetbotEnv("sideways")


def test_reward_is_the_seed_formula():
    assert forward_reward(0.5) == pytest.approx(np.exp(2.0) - 30.0)
    assert np.isfinite(forward_reward(0.0))


def test_aim_error_is_the_blocks_offset_from_the_line_of_travel(env):
    _, info = env.reset(options={"robot_pose": (-0.6, 0.0, 0.0)})
    assert info["aim_error"] == pytest.approx(0.0, abs=1e-3)
    for yaw in (0.15, -0.15):
        _, info = env.reset(options={"robot_pose": (-0.6, 0.0, yaw)})
        assert info["aim_error"] == pytest.approx(0.9 * np.sin(0.15), abs=2e-3)
    _, info = env.reset(options={"robot_pose": (-0.6, 0.0, np.pi)})  # block behind
    assert info["aim_error"] == pytest.approx(info["distance"], abs=2e-3)
    # Turning towards the block (clockwise, from yaw +0.15) shrinks it on the way.
    _, before = env.reset(options={"robot_pose": (-0.6, 0.0, 0.15)})
    errors = [env.step(np.array([1.0, -1.0]))[4]["aim_error"] for _ in range(10)]
    assert min(errors) < before["aim_error"] - 0.05
