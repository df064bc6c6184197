"""A seeded rollout of random frames for PPO's update tests (``ppo_update`` without an env)."""

from __future__ import annotations

from collections.abc import Callable

import torch

from jetbot_rt.train.model import ActorCritic, normal_log_prob
from jetbot_rt.train.rollout import Rollout


def random_rollout(model: ActorCritic, steps: int, envs: int = 2,
                   behaviour_shift: float | None = None,
                   state_of: Callable[[torch.Tensor], torch.Tensor] | None = None) -> Rollout:
    """``steps`` x ``envs`` random frames with the model's own actions (its mean plus noise),
    their log-probabilities and values, random rewards and no episode ends. With
    ``behaviour_shift`` the collecting weights' log-probabilities are the model's plus it;
    with ``state_of`` each step's privileged state is ``state_of`` of its preprocessed
    frames."""
    side = model.config.image_size
    gen = torch.Generator().manual_seed(0)
    frames = torch.randint(0, 256, (steps * envs, side, side, 3), generator=gen).float()
    with torch.no_grad():
        obs = model.preprocess(frames)
        mu, log_std, value = model.heads(obs)
        actions = mu + 0.3 * torch.randn(mu.shape, generator=gen)
        logprobs = normal_log_prob(actions, mu, log_std.exp()).sum(-1)
    shape = (steps, envs)
    behaviour = None if behaviour_shift is None else (logprobs + behaviour_shift).reshape(shape)
    states = None if state_of is None else state_of(obs)
    return Rollout(obs.reshape(*shape, *obs.shape[1:]), actions.reshape(*shape, 2),
                   logprobs.reshape(shape), torch.randn(shape, generator=gen),
                   torch.zeros(shape), value.reshape(shape), obs[:envs], torch.zeros(envs), [],
                   states=None if states is None else states.reshape(*shape, -1),
                   next_state=None if states is None else states[:envs],
                   behaviour_logprobs=behaviour)
