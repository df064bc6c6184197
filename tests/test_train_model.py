"""The actor-critic network: the action prior it starts from and the exported contract."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from jetbot_rt.train.env import POLICY_IMAGE_SIZE
from jetbot_rt.train.hyperparams import ModelConfig, OptionError
from jetbot_rt.train.model import ActorCritic, normal_log_prob

S = POLICY_IMAGE_SIZE


def test_a_fresh_policy_drives_forward_with_small_noise():
    torch.manual_seed(0)
    model = ActorCritic()
    images = torch.from_numpy(
        np.random.default_rng(0).integers(0, 256, (8, S, S, 3)).astype(np.float32))
    with torch.no_grad():
        mu, log_std, value = model(images)
    assert mu.shape == (8, 2) and log_std.shape == (8, 2) and value.shape == (8, 1)
    assert torch.allclose(mu, torch.full_like(mu, ModelConfig().init_mu), atol=0.05)
    assert torch.allclose(log_std, torch.full_like(log_std, ModelConfig().init_log_std))


def test_the_prior_is_configurable_and_round_trips_through_the_config_dict():
    config = ModelConfig(init_mu=0.0, init_log_std=-0.5)
    model = ActorCritic(ModelConfig.from_dict(config.to_dict()))
    with torch.no_grad():
        mu, log_std, _ = model(torch.zeros(2, S, S, 3))
    assert mu.abs().max() < 0.05 and torch.allclose(log_std, torch.full_like(log_std, -0.5))


def test_input_size_and_pooling_give_the_same_network_as_pooled_by_hand():
    torch.manual_seed(0)
    pooled = ActorCritic(ModelConfig(image_size=112, pool=2))
    torch.manual_seed(0)
    direct = ActorCritic(ModelConfig(image_size=56, pool=1))
    images = torch.from_numpy(
        np.random.default_rng(1).integers(0, 256, (3, 112, 112, 3)).astype(np.float32))
    by_hand = images.reshape(3, 56, 2, 56, 2, 3).mean((2, 4))
    with torch.no_grad():
        for got, want in zip(pooled(images), direct(by_hand), strict=True):
            assert torch.allclose(got, want, atol=1e-5)


def test_a_config_saved_before_image_size_existed_is_the_224_pooled_network():
    legacy = {k: v for k, v in ModelConfig().to_dict().items() if k not in ("image_size", "pool")}
    legacy["pool"] = 4
    config = ModelConfig.from_dict(legacy)
    assert (config.image_size, config.pool) == (224, 4)
    with pytest.raises(OptionError, match=r"model\.pool must divide image_size 64"):
        ModelConfig(image_size=64, pool=3)


@pytest.mark.parametrize("config", [
    ModelConfig(), ModelConfig(first_kernel=6, first_stride=4), ModelConfig(image_size=224, pool=4),
    ModelConfig(image_size=57, first_kernel=7, first_stride=3, channels=(3, 5, 7), hidden=9),
    ModelConfig(image_size=8, first_kernel=8, first_stride=8)])
def test_the_parameter_count_is_the_networks_without_building_it(config):
    assert config.parameter_count() == sum(p.numel() for p in ActorCritic(config).parameters())


@pytest.mark.parametrize(("options", "needle"), [
    ({"hidden": 0}, "model.hidden must be 1 .. 65536, got 0"),
    ({"hidden": True}, "model.hidden must be an integer, got True"),
    ({"image_size": 4}, "model.image_size must be 8 .. 1024"),
    ({"channels": (4, 4)}, "model.channels must be three integers"),
    ({"first_stride": 6}, "model.first_stride must be 1 .. first_kernel (5)"),
    ({"init_mu": float("nan")}, "model.init_mu must be a number in [-10, 10]"),
    ({"image_size": 1024, "hidden": 60_000}, "parameters, more than the 8,000,000"),
])
def test_a_network_option_out_of_range_names_the_option(options, needle):
    with pytest.raises(OptionError) as info:
        ModelConfig(**options)
    assert needle in str(info.value)
    assert info.value.name.startswith("model")


def test_the_first_layer_is_configurable_and_old_configs_keep_the_5x5_stride_2_one():
    from jetbot_rt.train.hyperparams import ppo_args

    forward = ActorCritic(ppo_args("forward").model)
    conv = forward.encoder[0]
    assert (conv.kernel_size, conv.stride, conv.padding) == ((6, 6), (4, 4), (1, 1))
    assert forward.encoder[:-3](torch.zeros(1, 3, S, S)).shape == (1, 32, 4, 4)
    with torch.no_grad():
        assert forward(torch.zeros(3, S, S, 3))[0].shape == (3, 2)
    saved = {k: v for k, v in ModelConfig().to_dict().items()
             if k not in ("first_kernel", "first_stride")}
    old = ActorCritic(ModelConfig.from_dict(saved)).encoder[0]
    assert (old.kernel_size, old.stride, old.padding) == ((5, 5), (2, 2), (2, 2))
    assert ppo_args("seek").model.first_stride == 2  # seek keeps the network it was tuned with
    with pytest.raises(OptionError, match="first_stride"):
        ModelConfig(first_kernel=3, first_stride=4)


def test_the_rollout_log_density_is_torchs_bit_for_bit():
    torch.manual_seed(0)
    mu, std = torch.randn(5, 2), torch.rand(5, 2) + 0.1
    x = torch.normal(mu, std)
    normal = torch.distributions.Normal(mu, std, validate_args=False)
    assert torch.equal(normal_log_prob(x, mu, std), normal.log_prob(x))


@pytest.mark.parametrize("preset", [None, "ACTIVE"])
def test_torch_threads_sleep_while_waiting_unless_the_user_says_otherwise(preset):
    """Spinning OpenMP threads made the update 6x slower on shared cores; the policy has to be
    in the environment before torch loads libgomp, i.e. when the train package is imported."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if preset:
        env["OMP_WAIT_POLICY"] = preset
    code = "import os, jetbot_rt.train, torch; print(os.environ['OMP_WAIT_POLICY'])"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True, timeout=120).stdout.split()
    assert out == [preset or "PASSIVE"]
