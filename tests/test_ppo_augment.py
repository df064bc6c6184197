"""PPO's ``--augment`` (DrAC): the random shift of a frame, and the regulariser that makes the
policy's mean and the image critic's value the same on a frame and its shifted copy."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from random_rollout import random_rollout

from jetbot_rt.train import ppo
from jetbot_rt.train.augment import random_shift
from jetbot_rt.train.hyperparams import CriticConfig, ModelConfig, OptionError, PPOArgs
from jetbot_rt.train.model import ActorCritic
from jetbot_rt.train.rollout import Rollout

SIZE = 16


def test_a_shift_moves_every_pixel_by_its_offset_and_repeats_the_edge():
    frames = torch.arange(2 * 3 * SIZE * SIZE, dtype=torch.float32).reshape(2, 3, SIZE, SIZE)
    offsets = np.random.default_rng(5).integers(0, 2 * 4 + 1, size=(2, 2))
    shifted = random_shift(frames, np.random.default_rng(5), shift=4)
    for n in range(2):
        dy, dx = (int(o) - 4 for o in offsets[n])
        for y, x in [(0, 0), (7, 9), (SIZE - 1, SIZE - 1), (3, SIZE - 2)]:
            source = frames[n, :, min(max(y + dy, 0), SIZE - 1), min(max(x + dx, 0), SIZE - 1)]
            assert torch.equal(shifted[n, :, y, x], source)
    assert not torch.equal(shifted, frames)  # the draw (seed 5) moves at least one frame


def test_no_shift_is_the_frame_and_a_draw_is_the_same_for_the_same_seed():
    frames = torch.rand(4, 3, SIZE, SIZE)
    assert torch.equal(random_shift(frames, np.random.default_rng(0), shift=0), frames)
    assert torch.equal(random_shift(frames, np.random.default_rng(3)),
                       random_shift(frames, np.random.default_rng(3)))


def _shift_gap(augment: float) -> float:
    """How far the policy's mean moves under shifts of the rollout's frames after ten updates
    with ``--augment`` ``augment``."""
    torch.manual_seed(1)
    model = ActorCritic(ModelConfig(image_size=SIZE, channels=(4, 4, 4), hidden=8))
    rollout = random_rollout(model, 16)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    options = PPOArgs(update_epochs=2, num_minibatches=2, augment=augment)
    advantages = torch.linspace(-1, 1, 32).reshape(16, 2)
    rng = np.random.default_rng(0)
    for _ in range(10):
        ppo.ppo_update(model, optimizer, rollout, advantages, advantages + 1, options, rng)
    obs = rollout.obs.reshape(-1, *rollout.obs.shape[2:])
    with torch.no_grad():
        gaps = [(model.heads(random_shift(obs, np.random.default_rng(s)))[0]
                 - model.heads(obs)[0]).abs().mean() for s in range(8)]
    return float(torch.stack(gaps).mean())


def test_the_regulariser_makes_the_policy_steadier_under_shifts():
    assert _shift_gap(10.0) < 0.5 * _shift_gap(0.0)


def test_a_negative_weight_is_refused():
    with pytest.raises(OptionError, match="augment"):
        PPOArgs(augment=-0.1).validate()


def _penalty(critic: bool) -> tuple[ActorCritic, torch.Tensor, torch.Tensor]:
    """The regulariser on 8 random frames, backpropagated; the unshifted frames' mean kept
    to read its gradient."""
    torch.manual_seed(2)
    config = ModelConfig(image_size=SIZE, channels=(4, 4, 4), hidden=8)
    model = ActorCritic(config, CriticConfig(state_size=3, hidden=8) if critic else None)
    obs = model.preprocess(torch.randint(0, 256, (8, SIZE, SIZE, 3)).float())
    mu, log_std, value = model.heads(obs)
    mu.retain_grad()
    dist = torch.distributions.Normal(mu, log_std.exp())
    critic_value = model.critic_value(torch.randn(8, 3)) if critic else value.squeeze(-1)
    penalty = ppo.shift_penalty(model, obs, dist, critic_value, not critic,
                                np.random.default_rng(0))
    penalty.backward()
    return model, penalty, mu


def test_the_frames_own_answer_is_the_fixed_side():
    _, penalty, mu = _penalty(critic=False)
    assert penalty > 0
    assert mu.grad is None  # detached: only the shifted frames' answers move


def test_the_image_critic_is_regularised_and_the_asymmetric_critic_is_not():
    image, _, _ = _penalty(critic=False)
    assert image.value_head.weight.grad.abs().sum() > 0
    asymmetric, _, _ = _penalty(critic=True)
    grad = asymmetric.value_head.weight.grad
    assert grad is None or not grad.any()
    assert all(p.grad is None or not p.grad.any() for p in asymmetric.critic.parameters())


def test_minibatches_of_one_sample_leave_the_weights_finite():
    torch.manual_seed(1)
    model = ActorCritic(ModelConfig(image_size=SIZE, channels=(4, 4, 4), hidden=8))
    rollout = random_rollout(model, 16)
    options = PPOArgs(update_epochs=1, num_minibatches=32)  # 32 samples: one each
    advantages = torch.linspace(-1, 1, 32).reshape(16, 2)
    ppo.ppo_update(model, torch.optim.Adam(model.parameters(), lr=1e-3), rollout, advantages,
                   advantages + 1, options, np.random.default_rng(0))
    assert all(torch.isfinite(p).all() for p in model.parameters())


def test_an_update_with_the_asymmetric_critic_leaves_the_image_value_head_alone():
    torch.manual_seed(1)
    config = ModelConfig(image_size=SIZE, channels=(4, 4, 4), hidden=8)
    model = ActorCritic(config, CriticConfig(state_size=3, hidden=8))
    plain = random_rollout(ActorCritic(config), 16)
    rollout = Rollout(*[getattr(plain, f) for f in ("obs", "actions", "logprobs", "rewards",
                                                     "dones", "values", "next_obs",
                                                     "next_done", "episodes")],
                      states=torch.randn(16, 2, 3), next_state=torch.randn(2, 3))
    before = model.value_head.weight.clone()
    advantages = torch.linspace(-1, 1, 32).reshape(16, 2)
    ppo.ppo_update(model, torch.optim.Adam(model.parameters(), lr=1e-2), rollout, advantages,
                   advantages + 1, PPOArgs(update_epochs=2, num_minibatches=2, augment=10.0),
                   np.random.default_rng(0))
    assert torch.equal(model.value_head.weight, before)  # the image critic is never trained
