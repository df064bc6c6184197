"""PPO's ``--overlap``: the workers collect the next rollout while the learner updates, with
the weights from before the update. The learner's view of a lagged rollout (its own
log-probabilities and values, the collecting weights' kept apart), the decoupled surrogate
that is PPO's where nothing lags, nothing in flight at the end, resume, and the refusals."""

from __future__ import annotations

import copy
import multiprocessing
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from random_rollout import random_rollout
from train_runner import train_main

from jetbot_rt.train import ppo
from jetbot_rt.train.hyperparams import ModelConfig, PPOArgs
from jetbot_rt.train.model import ActorCritic, normal_log_prob
from jetbot_rt.train.rollout import WorkerRollouts

pytest.importorskip("pybullet")

SIZE = 16


def _updated(behaviour_shift: float | None, epochs: int = 2,
             minibatches: int = 2) -> tuple[dict[str, torch.Tensor], float]:
    torch.manual_seed(1)
    model = ActorCritic(ModelConfig(image_size=SIZE, channels=(4, 4, 4), hidden=8))
    rollout = random_rollout(model, 4, behaviour_shift=behaviour_shift)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    options = PPOArgs(update_epochs=epochs, num_minibatches=minibatches)
    advantages = torch.linspace(-1, 1, 8).reshape(4, 2)
    stats = ppo.ppo_update(model, optimizer, rollout, advantages, advantages + 1, options,
                           np.random.default_rng(0))
    return {k: v.clone() for k, v in model.state_dict().items()}, stats.policy_loss


def test_the_decoupled_surrogate_is_ppos_where_nothing_lags():
    plain, plain_loss = _updated(None)
    same, same_loss = _updated(0.0)  # collected with the learner's own weights: weight 1
    less_likely, _ = _updated(-1.0)  # the learner's action more likely: truncated at 1
    assert same_loss == plain_loss
    for name in plain:
        assert torch.equal(plain[name], same[name]), name
        assert torch.equal(plain[name], less_likely[name]), name
    # the collecting weights made the samples e times likelier than the learner's: each is
    # weighed by 1/e; in one step over the whole rollout (every ratio 1) the loss is 1/e
    _, one_step = _updated(None, epochs=1, minibatches=1)
    _, lagged_one_step = _updated(1.0, epochs=1, minibatches=1)
    assert lagged_one_step == pytest.approx(one_step / np.e, rel=1e-5)


@dataclass
class Update:
    """What one update was given, beside what the model computes of it."""

    in_flight: bool
    """Whether the next rollout was being collected meanwhile."""
    lagged: bool
    """Whether the rollout carried the collecting weights' log-probabilities apart."""
    learners: float
    """max |rollout's log-probs and values - the model's own| at the update's start."""
    behaviours: float | None
    """max |collecting log-probs - the model's before the last update|, when lagged."""
    lag: float | None
    """max |the model's log-probs now - before the last update|: the update moved it."""


def _spying(monkeypatch) -> tuple[list[Update], list[WorkerRollouts]]:
    """``ppo_update`` and ``make_rollout_source`` wrapped: each update's ``Update``."""
    seen: list[Update] = []
    sources: list[WorkerRollouts] = []
    before: list[dict[str, torch.Tensor]] = []
    update, make_source = ppo.ppo_update, ppo.make_rollout_source

    def own(model, rollout):
        obs, actions = rollout.obs.flatten(0, 1), rollout.actions.flatten(0, 1)
        with torch.no_grad():
            mu, log_std, value = model.heads(obs)
            if rollout.states is not None:
                value = model.critic_value(rollout.states.flatten(0, 1))
            return normal_log_prob(actions, mu, log_std.exp()).sum(-1), value.flatten()

    def spy(model, optimizer, rollout, *args):
        logprobs, values = own(model, rollout)
        learners = max((rollout.logprobs.flatten() - logprobs).abs().max().item(),
                       (rollout.values.flatten() - values).abs().max().item())
        behaviours = lag = None
        if rollout.behaviour_logprobs is not None:
            earlier = copy.deepcopy(model)
            earlier.load_state_dict(before[-1])
            previous = own(earlier, rollout)[0]
            behaviours = (rollout.behaviour_logprobs.flatten() - previous).abs().max().item()
            lag = (logprobs - previous).abs().max().item()
        seen.append(Update(sources[-1].in_flight is not None,
                           rollout.behaviour_logprobs is not None, learners, behaviours, lag))
        before.append(copy.deepcopy(model.state_dict()))
        return update(model, optimizer, rollout, *args)

    def keep(*args):
        sources.append(make_source(*args))
        return sources[-1]

    monkeypatch.setattr(ppo, "ppo_update", spy)
    monkeypatch.setattr(ppo, "make_rollout_source", keep)
    return seen, sources


@pytest.mark.parametrize("critic", ["image", "state"])
def test_overlapped_training_lags_by_one_update_ends_with_nothing_in_flight_and_resumes(
        tmp_path, monkeypatch, critic):
    seen, sources = _spying(monkeypatch)
    args = PPOArgs(num_envs=2, num_steps=32, total_timesteps=256, out=str(tmp_path),
                   update_epochs=1, progress=False, overlap=True, critic=critic)
    summary = ppo.train(args)
    assert summary["global_step"] == 256 and summary["updates"] == 4
    assert isinstance(sources[0], WorkerRollouts) and sources[0].in_flight is None
    assert [u.in_flight for u in seen] == [True, True, True, False]
    assert [u.lagged for u in seen] == [False, True, True, True]
    for u in seen:
        # the learner's log-probabilities and values (the first rollout's from the workers'
        # onnxruntime copy of the same weights: within its ~1e-6 of torch)
        assert u.learners < 1e-4, u
    for u in seen[1:]:
        # collected with the weights before the last update, which moved them
        assert u.behaviours is not None and u.behaviours < 1e-4, u
        assert u.lag is not None and u.lag > 1e-3, u
    assert (tmp_path / "policy.onnx").stat().st_size > 0
    if critic == "state":
        return
    seen.clear()
    resumed = ppo.train(PPOArgs(num_envs=2, num_steps=32, total_timesteps=320,
                                out=str(tmp_path), update_epochs=1, progress=False,
                                overlap=True, resume=True))
    assert resumed["global_step"] == 320 and len(seen) == 1
    assert not seen[0].in_flight and not seen[0].lagged  # the last update: nothing prefetched


def test_an_error_in_the_update_with_a_rollout_in_flight_ends_the_workers(tmp_path,
                                                                          monkeypatch):
    calls = []
    update = ppo.ppo_update

    def failing(*args):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("the update failed")
        return update(*args)

    monkeypatch.setattr(ppo, "ppo_update", failing)
    args = PPOArgs(num_envs=2, num_steps=32, total_timesteps=1_000_000, out=str(tmp_path),
                   update_epochs=1, progress=False, overlap=True)
    with pytest.raises(RuntimeError, match="the update failed"):
        ppo.train(args)
    assert multiprocessing.active_children() == []  # ended, not waited for or left behind


@pytest.mark.parametrize(("flags", "needle"), [
    (("--workers", "0"), "--overlap needs the policy in the env workers"),
    (("--no-sample-in-workers",), "--overlap needs the policy in the env workers"),
    (("--curriculum", "--task", "seek", "--algo", "ppo"), "--overlap cannot run with curriculum"),
])
def test_overlap_where_it_cannot_run_is_one_line_and_exit_2(tmp_path, capsys, flags, needle):
    out = tmp_path / "run"
    code, _, err = train_main(capsys, "train", "--overlap", *flags, "--out", str(out))
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and needle in lines[0], lines
    assert not out.exists()
