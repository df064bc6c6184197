"""The actor-critic network: camera image in, wheel-command Gaussian and state value out.

It takes the exact tensor the runtime feeds an ONNX policy -- ``[N, S, S, 3]`` float32 RGB
in 0..255 (NHWC, the rl_games layout), S = ``ModelConfig.image_size`` -- and does its own
scaling (and, with ``pool`` > 1, area downsampling), so the exported graph needs no
preprocessing outside it. The env renders at S (56 by default, ``POLICY_IMAGE_SIZE``); a
network of a larger input (``image_size`` 224, ``pool`` 4) area-pools it to 56x56 first, so
the same convolutions serve both. About 0.2 M parameters (an rl_games network for this input
has ~19 M); 82 k with the 6x6 stride-4 first layer that forward's PPO default uses
(``first_kernel``, ``first_stride``).

With a ``CriticConfig`` (PPO's ``--critic state``) the network also has ``critic``, an MLP on
the task's privileged state: the asymmetric actor-critic. ``value`` and ``distribution`` then
take that state and the value comes from it; ``forward`` -- what is exported -- stays the
image-only actor (its ``value`` output is the image head's, which such a run never trains,
as a DAgger policy's). ``CriticConfig.predicts_state`` adds ``state_head``: a linear map from
the actor's features to that state (PPO's ``--predict-state``), also never exported.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from jetbot_rt.train.hyperparams import CriticConfig, ModelConfig

LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))
CRITIC = "critic"
"""The asymmetric critic's module (its weights are named ``critic.*``)."""
STATE_HEAD = "state_head"
"""The state prediction head's module (``--predict-state``; weights ``state_head.*``)."""
TRAINING_ONLY = (CRITIC, STATE_HEAD)
"""The modules a run trains that the exported actor (and the env workers' copies) lack."""


def normal_log_prob(x: torch.Tensor, mu: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """Per-dimension log density of ``Normal(mu, std)`` at ``x``, as torch's ``log_prob``
    computes it, without building a distribution object (PPO's rollout: 2 frames a step)."""
    return -((x - mu) ** 2) / (2 * std**2) - std.log() - LOG_SQRT_2PI


def _layer_init(layer: nn.Module, gain: float) -> nn.Module:
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


class ActorCritic(nn.Module):
    validate_args = False
    """Whether the action distribution checks its arguments (torch's default: yes). Off: at
    PPO's batch of 2 frames per step the checks cost about as much as the network itself
    (benchmarks/bench_train.py turns them on for its baseline)."""

    def __init__(self, config: ModelConfig = ModelConfig(),  # noqa: B008 (frozen)
                 critic: CriticConfig | None = None) -> None:
        super().__init__()
        self.config = config
        self.critic_config = critic
        """None: the value is the image head's (one network); else the asymmetric critic's."""
        c1, c2, c3 = config.channels
        kernel, stride, pad = config.first_kernel, config.first_stride, config.first_padding()
        side = config.feature_side()
        relu_gain = nn.init.calculate_gain("relu")
        self.encoder = nn.Sequential(
            _layer_init(nn.Conv2d(3, c1, kernel, stride=stride, padding=pad), relu_gain),
            nn.ReLU(),
            _layer_init(nn.Conv2d(c1, c2, 3, stride=2, padding=1), relu_gain),
            nn.ReLU(),
            _layer_init(nn.Conv2d(c2, c3, 3, stride=2, padding=1), relu_gain),
            nn.ReLU(),
            nn.Flatten(),
            _layer_init(nn.Linear(c3 * side * side, config.hidden), relu_gain),
            nn.ReLU(),
        )
        self.mu_head = _layer_init(nn.Linear(config.hidden, 2), 0.01)
        nn.init.constant_(self.mu_head.bias, config.init_mu)
        self.value_head = _layer_init(nn.Linear(config.hidden, 1), 1.0)
        self.log_std = nn.Parameter(torch.full((2,), float(config.init_log_std)))
        self.critic: nn.Module | None = None
        if critic is not None:  # built last: the actor's weights draw as without it
            self.critic = nn.Sequential(
                _layer_init(nn.Linear(critic.state_size, critic.hidden), math.sqrt(2)),
                nn.Tanh(),
                _layer_init(nn.Linear(critic.hidden, critic.hidden), math.sqrt(2)),
                nn.Tanh(),
                _layer_init(nn.Linear(critic.hidden, 1), 1.0),
            )
        self.state_head: nn.Module | None = None
        if critic is not None and critic.predicts_state:
            self.state_head = _layer_init(nn.Linear(config.hidden, critic.state_size), 1.0)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``obs``: ``[N, S, S, 3]`` RGB, 0..255 (any float or uint8 dtype), S = image_size.

        Returns ``mu`` ``[N, 2]``, ``log_std`` ``[N, 2]``, ``value`` ``[N, 1]``.
        """
        return self.heads(self.preprocess(obs))

    def preprocess(self, obs: torch.Tensor) -> torch.Tensor:
        """Fixed part: NHWC 0..255 to NCHW 0..1, area-pooled to 1/pool size. Nothing to
        learn, so PPO runs it once per collected frame instead of once per epoch."""
        pool, side = self.config.pool, self.config.image_size // self.config.pool
        x = obs.float()
        if pool > 1:
            x = x.reshape(-1, side, pool, side, pool, 3).sum((2, 4))
        return x.permute(0, 3, 1, 2) * (1.0 / (pool * pool * 255.0))

    def heads(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``x``: output of ``preprocess``."""
        features = self.encoder(x)
        mu = self.mu_head(features)
        return mu, self.log_std.expand_as(mu), self.value_head(features)

    def critic_value(self, state: torch.Tensor | None) -> torch.Tensor:
        """The asymmetric critic's value of privileged states ``[N, state_size]``, ``[N]``."""
        if self.critic is None or state is None:
            raise ValueError("critic_value needs the asymmetric critic and the state it reads")
        return self.critic(state).squeeze(-1)

    def value(self, x: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        """State value of preprocessed observations, ``[N]``; with the asymmetric critic, of
        their privileged ``state`` (``x`` unused)."""
        if self.critic is not None:
            return self.critic_value(state)
        return self.heads(x)[2].squeeze(-1)

    def distribution(self, x: torch.Tensor, state: torch.Tensor | None = None
                     ) -> tuple[torch.distributions.Normal, torch.Tensor]:
        """Action distribution and value of preprocessed observations (with the asymmetric
        critic, the value of their privileged ``state``)."""
        normal, value, _ = self.distribution_and_state(x, state)
        return normal, value

    def distribution_and_state(self, x: torch.Tensor, state: torch.Tensor | None = None
                               ) -> tuple[torch.distributions.Normal, torch.Tensor,
                                          torch.Tensor | None]:
        """``distribution``'s, and ``state_head``'s prediction of the state from the same
        features (None without a state head)."""
        features = self.encoder(x)
        mu = self.mu_head(features)
        normal = torch.distributions.Normal(mu, self.log_std.expand_as(mu).exp(),
                                            validate_args=self.validate_args)
        predicted = None if self.state_head is None else self.state_head(features)
        if self.critic is not None:
            return normal, self.critic_value(state), predicted
        return normal, self.value_head(features).squeeze(-1), predicted

    def actor_state_dict(self) -> dict[str, torch.Tensor]:
        """The weights of the image network alone (``forward``'s, what is exported and what
        the env workers' copies run): ``state_dict`` without the critic's."""
        return {name: weight for name, weight in self.state_dict().items()
                if name.split(".", 1)[0] not in TRAINING_ONLY}

    def critic_parameters(self) -> list[nn.Parameter]:
        return [] if self.critic is None else list(self.critic.parameters())

    def state_head_parameters(self) -> list[nn.Parameter]:
        return [] if self.state_head is None else list(self.state_head.parameters())

    def actor_parameters(self) -> list[nn.Parameter]:
        critic = {id(p) for p in self.critic_parameters() + self.state_head_parameters()}
        return [p for p in self.parameters() if id(p) not in critic]


