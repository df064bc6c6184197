"""PPO's ``--target-kl``: an update stops its epochs once the approximate KL divergence from
the collecting policy passes it (CleanRL's early stop)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch
from test_train_balance import _rollout

from jetbot_rt.train import ppo
from jetbot_rt.train.hyperparams import ModelConfig, PPOArgs
from jetbot_rt.train.model import ActorCritic

pytest.importorskip("pybullet")

CONFIG = ModelConfig(image_size=16, channels=(4, 4, 4), hidden=8)


def _update(target_kl: float | None, epochs: int = 4) -> tuple[ppo.UpdateStats, dict]:
    torch.manual_seed(1)
    model = ActorCritic(CONFIG)
    rollout = _rollout(model, 8, 2, torch.Generator().manual_seed(0))
    advantages = torch.linspace(-1, 1, 16).reshape(8, 2)
    options = PPOArgs(update_epochs=epochs, num_minibatches=2, target_kl=target_kl)
    stats = ppo.ppo_update(model, torch.optim.Adam(model.parameters(), lr=0.05), rollout,
                           advantages, advantages + 1, options, np.random.default_rng(0))
    return stats, model.state_dict()


def _same(a: dict, b: dict) -> bool:
    return all(torch.equal(a[name], b[name]) for name in a)


def test_an_update_stops_after_the_epoch_that_passes_the_target():
    every, every_weights = _update(None)
    assert every.epochs == 4 and every.approx_kl > 1e-6  # lr 0.05: the policy moves
    stopped, stopped_weights = _update(1e-9)
    _, one_weights = _update(None, epochs=1)
    assert stopped.epochs == 1 and _same(stopped_weights, one_weights)
    unreached, unreached_weights = _update(1e9)
    assert unreached.epochs == 4 and _same(unreached_weights, every_weights)
    assert not _same(one_weights, every_weights)


def test_a_run_with_a_target_writes_the_epochs_of_each_update(tmp_path):
    out = tmp_path / "run"
    summary = ppo.train(PPOArgs(num_envs=2, num_steps=16, total_timesteps=64, out=str(out),
                                update_epochs=3, target_kl=1e-9, progress=False, workers=0))
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert len(rows) == summary["updates"] == 2
    assert [row["epochs"] for row in rows] == ["1", "1"]

