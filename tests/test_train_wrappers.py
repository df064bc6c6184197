"""The trainer's reward lives in wrappers, not in the registered env; PPOArgs come from the
task's defaults, a [train] table and the command line, in that order."""

from __future__ import annotations

import numpy as np
import pytest

from jetbot_rt.errors import UsageError
from jetbot_rt.train.hyperparams import TASK_DEFAULTS, ModelConfig, PPOArgs, ppo_args
from jetbot_rt.train.wrappers import KeepInfo, Shaping, make_train_env, symlog

pytest.importorskip("pybullet")


def test_shaping_sums_to_the_potential_difference_and_the_env_keeps_its_reward():
    shaping = Shaping("none", shaping_coef=10.0, aim_coef=5.0)
    env = make_train_env("seek", None, shaping)
    plain = make_train_env("seek", None, Shaping("none"))
    try:
        _, first = env.reset(seed=3)
        plain.reset(seed=3)
        total = plain_total = 0.0
        for _ in range(20):
            _, reward, _, _, info = env.step(np.array([0.8, 0.5]))
            total += reward
            plain_total += plain.step(np.array([0.8, 0.5]))[1]
        expected = (10.0 * (first["distance"] - info["distance"])
                    + 5.0 * (first["aim_error"] - info["aim_error"]))
        assert total - plain_total == pytest.approx(expected, abs=1e-9)
        assert plain_total == 0.0  # seek's own reward: 1 on success only
    finally:
        env.close()
        plain.close()


def test_outcome_bonus_and_episode_statistics_carry_the_true_return():
    env = make_train_env("seek", None, Shaping("none", success_bonus=7.0))
    try:
        env.reset(seed=0)
        gx, gy = env.unwrapped.scene.piece("goal").xy
        env.reset(seed=0, options={"robot_pose": (gx - 0.13, gy, 0.0)})
        _, reward, terminated, _, info = env.step(np.zeros(2))
        assert terminated and reward == pytest.approx(8.0)
        assert info["episode"]["r"] == pytest.approx(1.0)  # the task's reward, unshaped
    finally:
        env.close()


def test_step_penalty_is_paid_every_step_and_the_true_return_is_unchanged():
    env = make_train_env("seek", None, Shaping("none", success_bonus=7.0, step_penalty=0.25))
    try:
        env.reset(seed=0)
        rewards = [env.step(np.zeros(2))[1] for _ in range(3)]
        assert rewards == [pytest.approx(-0.25)] * 3
        gx, gy = env.unwrapped.scene.piece("goal").xy
        env.reset(seed=0, options={"robot_pose": (gx - 0.13, gy, 0.0)})
        _, reward, terminated, _, info = env.step(np.zeros(2))
        assert terminated and reward == pytest.approx(1.0 + 7.0 - 0.25)
        assert info["episode"]["r"] == pytest.approx(1.0)
    finally:
        env.close()


def test_keep_info_passes_on_only_the_keys_asked_for_and_the_rest_unchanged():
    env = KeepInfo(make_train_env("forward", None, Shaping("none")), ("distance", "episode"))
    full = make_train_env("forward", None, Shaping("none"))
    try:
        assert env.reset(seed=2)[1].keys() == {"distance"}
        full.reset(seed=2)
        obs, reward, terminated, truncated, info = env.step(np.array([0.5, 0.4]))
        want = full.step(np.array([0.5, 0.4]))
        assert info == {"distance": want[4]["distance"]} and "pose" in want[4]
        assert np.array_equal(obs, want[0]) and (reward, terminated, truncated) == want[1:4]
    finally:
        env.close()
        full.close()


def test_symlog_and_bad_transform():
    assert symlog(np.e - 1) == pytest.approx(1.0) and symlog(-(np.e - 1)) == pytest.approx(-1.0)
    with pytest.raises(UsageError, match="unknown reward transform"):
        Shaping("cube")


def test_ppo_args_precedence_dataclass_task_overrides():
    forward = ppo_args("forward")
    assert forward.shaping_coef == TASK_DEFAULTS["forward"]["shaping_coef"]
    seek = ppo_args("seek")
    assert seek.total_timesteps == TASK_DEFAULTS["seek"]["total_timesteps"]
    assert seek.model.init_mu == TASK_DEFAULTS["seek"]["model"]["init_mu"]
    mine = ppo_args("seek", {"learning_rate": 0.01, "model": {"hidden": 64}})
    assert mine.learning_rate == 0.01 and mine.model.hidden == 64
    assert mine.model.init_mu == TASK_DEFAULTS["seek"]["model"]["init_mu"]
    assert mine.model.channels == ModelConfig().channels
    with pytest.raises(UsageError, match="unknown training option"):
        ppo_args("seek", {"learnin_rate": 0.01})
    with pytest.raises(UsageError, match="unknown model option"):
        ppo_args("seek", {"model": {"width": 3}})
    with pytest.raises(UsageError, match="unknown task"):
        ppo_args("sideways")


def test_every_ppo_field_is_a_flag_and_a_train_table_key(tmp_path):
    import dataclasses

    from jetbot_rt.train.cli import build_parser
    from jetbot_rt.train.flags import FLAG_NAMES, overrides
    from jetbot_rt.train.hyperparams import read_config_file

    parser = build_parser()
    help_text = parser._subparsers._group_actions[0].choices["train"].format_help()
    for spec in dataclasses.fields(PPOArgs):
        if spec.name not in ("task", "config", "model"):
            flag = FLAG_NAMES.get(spec.name, "--" + spec.name.replace("_", "-"))
            assert flag in help_text, spec.name
    for spec in dataclasses.fields(ModelConfig):
        assert "--model-" + spec.name.replace("_", "-") in help_text, spec.name
    toml = tmp_path / "train.toml"
    toml.write_text("[actions]\nmax_speed = 0.25\n[train]\ngamma = 0.9\nnum_steps = 64\n"
                    "[train.model]\nhidden = 32\n")
    config, table = read_config_file(str(toml))
    args = parser.parse_args(["train", "--task", "seek", "--num-steps", "32",
                              "--model-channels", "8", "8", "8", "--no-anneal-lr"])
    ppo = ppo_args("seek", overrides(args, table))
    assert config.actions.max_speed == 0.25
    assert (ppo.gamma, ppo.num_steps, ppo.anneal_lr) == (0.9, 32, False)
    assert ppo.model.hidden == 32 and ppo.model.channels == (8, 8, 8)
