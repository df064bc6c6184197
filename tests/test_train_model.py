"""The actor-critic network: the action prior it starts from and the exported contract."""

from __future__ import annotations

import numpy as np
import torch

from jetbot_rt.train.model import ActorCritic, ModelConfig


def test_a_fresh_policy_drives_forward_with_small_noise():
    torch.manual_seed(0)
    model = ActorCritic()
    images = torch.from_numpy(
        np.random.default_rng(0).integers(0, 256, (8, 224, 224, 3)).astype(np.float32))
    with torch.no_grad():
        mu, log_std, value = model(images)
    assert mu.shape == (8, 2) and log_std.shape == (8, 2) and value.shape == (8, 1)
    assert torch.allclose(mu, torch.full_like(mu, ModelConfig().init_mu), atol=0.05)
    assert torch.allclose(log_std, torch.full_like(log_std, ModelConfig().init_log_std))


def test_the_prior_is_configurable_and_round_trips_through_the_config_dict():
    config = ModelConfig(init_mu=0.0, init_log_std=-0.5)
    model = ActorCritic(ModelConfig.from_dict(config.to_dict()))
    with torch.no_grad():
        mu, log_std, _ = model(torch.zeros(2, 224, 224, 3))
    assert mu.abs().max() < 0.05 and torch.allclose(log_std, torch.full_like(log_std, -0.5))
