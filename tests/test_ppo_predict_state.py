"""PPO's ``--predict-state W``: with the asymmetric critic, a linear head on the actor's image
features learns to predict the critic's privileged state; it trains the encoder, never reaches
the exported actor, and its checkpoint resumes only as it was trained."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from random_rollout import random_rollout
from train_runner import train_main

from jetbot_rt.tasks.seek import Seek
from jetbot_rt.train import ppo
from jetbot_rt.train.checkpoint import load_checkpoint
from jetbot_rt.train.hyperparams import (
    CriticConfig,
    ModelConfig,
    OptionError,
    PPOArgs,
    critic_config,
    ppo_args,
)
from jetbot_rt.train.model import ActorCritic
from jetbot_rt.train.rollout import Rollout

SIZE = 16
STATE = 3


def _colour_means(obs: torch.Tensor) -> torch.Tensor:
    """A frame's state: its three colours' means (what the head can learn from the frame)."""
    return obs.mean((2, 3))


def _state_error(weight: float, updates: int = 30) -> tuple[float, float]:
    """The head's squared error on the rollout before and after ``updates`` updates with
    ``--predict-state`` ``weight``."""
    torch.manual_seed(1)
    model = ActorCritic(ModelConfig(image_size=SIZE, channels=(4, 4, 4), hidden=8),
                        CriticConfig(STATE, 8, predicts_state=True))
    rollout = random_rollout(model, 16, state_of=_colour_means)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    options = PPOArgs(update_epochs=2, num_minibatches=2, critic="state", predict_state=weight)
    advantages = torch.zeros(16, 2)
    rng = np.random.default_rng(0)
    errors = []
    for _ in range(updates):
        stats = ppo.ppo_update(model, optimizer, rollout, advantages, advantages, options, rng)
        errors.append(stats.state_loss)
    return errors[0], errors[-1]


def test_the_head_learns_the_state_from_the_frames_and_weight_zero_leaves_it():
    first, last = _state_error(1.0)
    assert last < 0.1 * first
    first, last = _state_error(0.0)
    assert last > 0.5 * first  # its error is reported, but it does not learn


def test_the_exported_actor_and_the_workers_copies_lack_the_head():
    config = ModelConfig(image_size=SIZE, channels=(4, 4, 4), hidden=8)
    model = ActorCritic(config, CriticConfig(STATE, 8, predicts_state=True))
    assert model.state_head is not None
    assert model.actor_state_dict().keys() == ActorCritic(config).state_dict().keys()
    head = {id(p) for p in model.state_head_parameters()}
    assert head and not head & {id(p) for p in model.actor_parameters()}
    assert not head & {id(p) for p in model.critic_parameters()}
    # the actor's weights draw as without the head (it is built after them)
    torch.manual_seed(4)
    plain = ActorCritic(config, CriticConfig(STATE, 8))
    torch.manual_seed(4)
    with_head = ActorCritic(config, CriticConfig(STATE, 8, predicts_state=True))
    for name, weight in plain.state_dict().items():
        assert torch.equal(with_head.state_dict()[name], weight), name


@pytest.mark.parametrize(("fields", "needle"), [
    ({"predict_state": -0.5, "critic": "state"}, "predict_state.*>= 0"),
    ({"predict_state": 1.0}, "predict_state.*critic"),
])
def test_a_bad_weight_or_the_image_critic_is_refused(fields, needle):
    with pytest.raises(OptionError, match=needle):
        PPOArgs(**fields).validate()


def test_the_config_round_trips_and_older_checkpoints_still_read():
    assert CriticConfig.from_dict({"state_size": 4, "hidden": 8}) == CriticConfig(4, 8)
    config = CriticConfig(4, 8, predicts_state=True)
    assert CriticConfig.from_dict(config.to_dict()) == config
    assert CriticConfig(4, 8).to_dict() == {"state_size": 4, "hidden": 8}
    with pytest.raises(OptionError, match="predicts_state"):
        CriticConfig.from_dict({"state_size": 4, "hidden": 8, "predicts_state": "yes"})
    with pytest.raises(OptionError, match="critic"):
        CriticConfig.from_dict({"state_size": 4, "hidden": 8, "extra": 1})
    head = (ModelConfig().hidden + 1) * 4
    assert config.parameter_count(ModelConfig()) == CriticConfig(4, 8).parameter_count() + head


@pytest.fixture(scope="module")
def predict_run(tmp_path_factory) -> Path:
    pytest.importorskip("pybullet")
    from jetbot_rt.train.cli import main

    out = tmp_path_factory.mktemp("predict_state")
    assert main(["train", "--task", "seek", "--algo", "ppo", "--num-steps", "64",
                 "--update-epochs", "1", "--num-minibatches", "2", "--num-envs", "1",
                 "--workers", "0", "--model-image-size", "8", "--seed", "3", "--no-progress",
                 "--critic", "state", "--predict-state", "1", "--timesteps", "128",
                 "--out", str(out)]) == 0
    return out


def test_a_seek_run_logs_the_error_and_exports_the_actor_alone(predict_run):
    rows = (predict_run / "metrics.csv").read_text().splitlines()
    assert rows[0].split(",")[-1] == ppo.STATE_LOSS
    assert all(float(r.split(",")[-1]) > 0 for r in rows[1:])
    state = torch.load(predict_run / "checkpoint.pt", weights_only=True)
    width = len(Seek.critic_state_names)
    assert state["critic"] == {"state_size": width, "hidden": 64, "predicts_state": True}
    assert state["model"]["state_head.weight"].shape == (width, 128)


def test_resume_needs_the_same_head_and_init_keeps_actor_and_critic(predict_run, tmp_path,
                                                                    capsys):
    from jetbot_rt.train.run_dir import starting_model

    run = tmp_path / "run"
    shutil.copytree(predict_run, run)
    before = (run / "metrics.csv").read_text()
    code, _, err = train_main(capsys, "train", "--task", "seek", "--algo", "ppo",
                              "--num-steps", "64", "--num-envs", "1", "--workers", "0",
                              "--model-image-size", "8", "--no-progress", "--critic", "state",
                              "--timesteps", "192", "--resume", "--out", str(run))
    assert code == 2 and err.count("\n") == 1
    assert "was trained with --predict-state, not without" in err
    assert (run / "metrics.csv").read_text() == before
    trained = torch.load(predict_run / "checkpoint.pt", weights_only=True)["model"]
    options = ppo_args("seek", {"critic": "state", "init": str(predict_run / "checkpoint.pt")})
    model, _ = starting_model(options, None, "ppo", critic_config(options))
    assert model.state_head is None and model.critic is not None
    assert model.state_dict().keys() == {n for n in trained if not n.startswith("state_head")}
    for name, weight in model.state_dict().items():
        assert torch.equal(weight, trained[name]), name
    assert load_checkpoint(predict_run / "checkpoint.pt").model().state_head is not None


def test_the_error_is_in_units_of_each_values_spread():
    """A head that answers 0 (the standardised mean) scores 1 whatever each value's scale."""
    model = ActorCritic(ModelConfig(image_size=SIZE, channels=(4, 4, 4), hidden=8),
                        CriticConfig(STATE, 8, predicts_state=True))
    torch.nn.init.zeros_(model.state_head.weight)
    torch.nn.init.zeros_(model.state_head.bias)
    rollout = random_rollout(model, 16, state_of=_colour_means)
    rollout.states[..., 0] = rollout.states[..., 0] * 1000 + 5  # one value far larger
    options = PPOArgs(update_epochs=1, num_minibatches=1, critic="state", predict_state=1e-9,
                      learning_rate=0.0)
    optimizer = torch.optim.Adam(model.parameters(), lr=0.0)
    stats = ppo.ppo_update(model, optimizer, rollout, torch.zeros(16, 2), torch.zeros(16, 2),
                           options, np.random.default_rng(0))
    assert stats.state_loss == pytest.approx(1.0, rel=1e-4)


def test_a_rollout_of_one_step_gives_a_finite_error():
    model = ActorCritic(ModelConfig(image_size=SIZE, channels=(4, 4, 4), hidden=8),
                        CriticConfig(STATE, 8, predicts_state=True))
    whole = random_rollout(model, 16, state_of=_colour_means)
    one = Rollout(*(t[:1, :1] for t in (whole.obs, whole.actions, whole.logprobs,
                                        whole.rewards, whole.dones, whole.values)),
                  whole.obs[0, :1], torch.zeros(1), [], states=whole.states[:1, :1],
                  next_state=whole.states[0, :1])
    options = PPOArgs(update_epochs=1, num_minibatches=1, critic="state", predict_state=1.0)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    stats = ppo.ppo_update(model, optimizer, one, torch.ones(1, 1), torch.ones(1, 1), options,
                           np.random.default_rng(0))
    assert np.isfinite(stats.state_loss)
    assert all(torch.isfinite(p).all() for p in model.parameters())
