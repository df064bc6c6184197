"""PPO's ``--balance``: a rollout is ``num_envs * num_steps`` env steps in all, each worker
stepping until the workers together have them (a worker's stop on the shared count is
test_train_sampler.py's). The learner's advantages, reward normalisation and update read each
env's own steps and never the padding; training runs with and without ``--overlap`` and
leaves no shared memory behind."""

from __future__ import annotations

from multiprocessing import shared_memory

import numpy as np
import pytest
import torch
from train_runner import train_main

from jetbot_rt.train import ppo
from jetbot_rt.train.hyperparams import ModelConfig, PPOArgs
from jetbot_rt.train.model import ActorCritic
from jetbot_rt.train.rollout import Rollout
from jetbot_rt.train.sampler import normalize_segment, stack_segments

pytest.importorskip("pybullet")


def test_ragged_advantages_are_each_envs_own():
    gen = torch.Generator().manual_seed(0)
    lengths = torch.tensor([5, 8, 3])
    rewards, values = torch.randn(8, 3, generator=gen), torch.randn(8, 3, generator=gen)
    dones = (torch.rand(8, 3, generator=gen) < 0.3).float()
    next_value, next_done = torch.randn(3, generator=gen), torch.tensor([0.0, 1.0, 1.0])
    advantages, returns = ppo.gae(rewards, values, dones, next_value, next_done, 0.9, 0.8,
                                  lengths)
    for env, length in enumerate(lengths.tolist()):
        own = slice(0, length), slice(env, env + 1)
        want, _ = ppo.gae(rewards[own], values[own], dones[own], next_value[env:env + 1],
                          next_done[env:env + 1], 0.9, 0.8)
        assert torch.allclose(advantages[own], want, atol=1e-6), env
        assert torch.all(advantages[length:, env] == 0)
    assert torch.equal(returns, advantages + values)
    full, _ = ppo.gae(rewards, values, dones, next_value, next_done, 0.9, 0.8)
    same, _ = ppo.gae(rewards, values, dones, next_value, next_done, 0.9, 0.8,
                      torch.full((3,), 8))
    assert torch.allclose(full, same, atol=1e-6)


class Normaliser:
    """The state ``normalize_segment`` reads and updates (``NormalizeReward``'s)."""

    def __init__(self, envs: int) -> None:
        from gymnasium.wrappers.utils import RunningMeanStd

        self.accumulated_reward = np.zeros(envs)
        self.return_rms = RunningMeanStd(shape=())
        self.gamma, self.epsilon, self.update_running_mean = 0.9, 1e-8, True


def test_reward_normalisation_reads_each_envs_steps_only():
    rng = np.random.default_rng(1)
    rewards = rng.normal(0.0, 3.0, (4, 2))
    rewards[2:, 1] = np.nan  # padding: must not reach any output or state
    no = np.zeros((4, 2), dtype=bool)
    normaliser = Normaliser(2)
    out = normalize_segment(normaliser, 5.0, rewards, no, no, np.array([4, 2]))
    assert np.isfinite(out).all() and (out[2:, 1] == 0).all()
    assert normaliser.accumulated_reward[1] == pytest.approx(0.9 * rewards[0, 1] + rewards[1, 1])
    assert normaliser.return_rms.count == pytest.approx(6 + 1e-4)  # 6 env steps, not 8
    full = rng.normal(0.0, 3.0, (4, 2))
    a, b = Normaliser(2), Normaliser(2)
    np.testing.assert_array_equal(normalize_segment(a, 5.0, full, no, no),
                                  normalize_segment(b, 5.0, full, no, no, np.array([4, 4])))


def test_padded_segments_stack_to_the_longest_with_their_lengths():
    short = {"rewards": np.ones(2), "obs": np.ones((2, 3)), "next_obs": np.ones(3),
             "episodes": [(1, 5.0, 0.0, 1.0)]}
    long = {"rewards": np.ones(4), "obs": np.ones((4, 3)), "next_obs": np.zeros(3),
            "episodes": [(0, 2.0, 0.0, 0.0)]}
    stacked = stack_segments((short, long))
    assert stacked["lengths"].tolist() == [2, 4] and stacked["obs"].shape == (4, 2, 3)
    assert (stacked["rewards"][2:, 0] == 0).all() and (stacked["rewards"][:, 1] == 1).all()
    assert stacked["episodes"] == [(0, 1, 2.0, 0.0, 0.0), (1, 0, 5.0, 0.0, 1.0)]


def _rollout(model: ActorCritic, steps: int, envs: int, gen: torch.Generator,
             lengths: torch.Tensor | None = None) -> Rollout:
    size = model.config.image_size
    frames = torch.randint(0, 256, (steps * envs, size, size, 3), generator=gen).float()
    obs = model.preprocess(frames)
    shape = (steps, envs)
    return Rollout(obs.reshape(*shape, *obs.shape[1:]), torch.randn(*shape, 2, generator=gen),
                   torch.randn(shape, generator=gen) - 2, torch.zeros(shape), torch.zeros(shape),
                   torch.zeros(shape), obs[:envs], torch.zeros(envs), [], lengths=lengths)


def test_the_update_reads_no_padding():
    """A 4-step, 2-env rollout whose env 1 has 2 steps, its padding NaN, updates the model as
    the 6 real steps laid out as one env do."""
    config = ModelConfig(image_size=16, channels=(4, 4, 4), hidden=8)
    options = PPOArgs(update_epochs=2, num_minibatches=2)
    torch.manual_seed(1)
    padded_model = ActorCritic(config)
    compact_model = ActorCritic(config)
    compact_model.load_state_dict(padded_model.state_dict())
    padded = _rollout(padded_model, 4, 2, torch.Generator().manual_seed(0), torch.tensor([4, 2]))
    advantages = torch.linspace(-1, 1, 8).reshape(4, 2)
    kept = padded.valid.reshape(-1)
    assert kept.tolist() == [True, True, True, True, True, False, True, False]
    for tensor in (padded.obs, padded.actions, padded.logprobs, advantages):
        tensor.reshape(8, -1)[~kept] = float("nan")

    def compact(tensor: torch.Tensor) -> torch.Tensor:
        return tensor.reshape(8, *tensor.shape[2:])[kept][:, None]

    one_env = Rollout(compact(padded.obs), compact(padded.actions), compact(padded.logprobs),
                      compact(padded.rewards), compact(padded.dones), compact(padded.values),
                      padded.obs[0, :1], torch.zeros(1), [])
    optimizers = [torch.optim.Adam(m.parameters(), lr=1e-2)
                  for m in (padded_model, compact_model)]
    ppo.ppo_update(padded_model, optimizers[0], padded, advantages, advantages + 1, options,
                   np.random.default_rng(0))
    ppo.ppo_update(compact_model, optimizers[1], one_env, compact(advantages),
                   compact(advantages) + 1, options, np.random.default_rng(0))
    assert padded.steps == 6
    for name, weight in padded_model.state_dict().items():
        assert torch.isfinite(weight).all(), name
        assert torch.allclose(weight, compact_model.state_dict()[name], atol=1e-6), name


def test_a_remainder_minibatch_of_one_sample_is_not_made():
    """7 samples in 2 minibatches were 3, 3 and 1; one sample's advantage has no std (NaN)."""
    config = ModelConfig(image_size=16, channels=(4, 4, 4), hidden=8)
    torch.manual_seed(2)
    model = ActorCritic(config)
    rollout = _rollout(model, 7, 1, torch.Generator().manual_seed(3))
    ppo.ppo_update(model, torch.optim.Adam(model.parameters(), lr=1e-2), rollout,
                   torch.linspace(-1, 1, 7)[:, None], torch.zeros(7, 1),
                   PPOArgs(update_epochs=1, num_minibatches=2), np.random.default_rng(0))
    assert all(torch.isfinite(w).all() for w in model.state_dict().values())


def test_balanced_training_runs_with_and_without_overlap_and_frees_its_counters(
        tmp_path, monkeypatch):
    seen, names = [], []
    update, make_source = ppo.ppo_update, ppo.make_rollout_source

    def spy(model, optimizer, rollout, *args):
        seen.append(rollout.lengths.tolist())
        return update(model, optimizer, rollout, *args)

    def keep(*args):
        source = make_source(*args)
        names.append(source.shared.name)
        return source

    monkeypatch.setattr(ppo, "ppo_update", spy)
    monkeypatch.setattr(ppo, "make_rollout_source", keep)
    for overlap in (False, True):
        seen.clear()
        summary = ppo.train(PPOArgs(num_envs=2, num_steps=32, total_timesteps=256,
                                    out=str(tmp_path / str(overlap)), update_epochs=1,
                                    progress=False, balance=True, overlap=overlap))
        assert len(seen) == summary["updates"] >= 3
        for lengths in seen:
            assert sum(lengths) >= 64 and all(8 <= n <= 64 for n in lengths), lengths
        assert summary["global_step"] == sum(map(sum, seen))
        assert (tmp_path / str(overlap) / "policy.onnx").stat().st_size > 0
    for name in names:
        with pytest.raises(FileNotFoundError):
            shared_memory.SharedMemory(name=name)


def test_balance_where_it_cannot_run_is_one_line_and_exit_2(tmp_path, capsys):
    out = tmp_path / "run"
    code, _, err = train_main(capsys, "train", "--balance", "--workers", "0", "--out", str(out))
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, lines
    assert "--balance needs the policy in the env workers" in lines[0]
    assert not out.exists()


def test_a_balanced_overlapped_run_ends_with_nothing_in_flight(tmp_path, monkeypatch):
    """Balanced rollouts overshoot num_envs * num_steps; a prefetch planned on that size
    left one in flight at the end of a normal run, whose workers were then killed (their
    clean-up skipped) as after Ctrl-C."""
    from jetbot_rt.train.rollout import WorkerRollouts

    at_close = []
    close = WorkerRollouts.close

    def spy(self, interrupted):
        at_close.append((interrupted, self.waiting, self.in_flight))
        return close(self, interrupted)

    monkeypatch.setattr(WorkerRollouts, "close", spy)
    summary = ppo.train(PPOArgs(num_envs=4, num_steps=16, total_timesteps=134,
                                out=str(tmp_path), update_epochs=1, progress=False,
                                balance=True, overlap=True))
    assert summary["global_step"] >= 134
    assert at_close == [(False, False, None)]


def test_a_stop_while_the_run_sets_up_ends_the_workers_and_frees_the_counters(
        tmp_path, monkeypatch):
    import multiprocessing

    names = []
    make_source = ppo.make_rollout_source

    def keep(*args):
        source = make_source(*args)
        names.append(source.shared.name)
        return source

    def interrupted(directory):
        raise KeyboardInterrupt

    monkeypatch.setattr(ppo, "make_rollout_source", keep)
    monkeypatch.setattr(ppo, "_tensorboard", interrupted)
    with pytest.raises(KeyboardInterrupt):
        ppo.train(PPOArgs(num_envs=2, num_steps=16, total_timesteps=64, out=str(tmp_path),
                          progress=False, balance=True))
    assert multiprocessing.active_children() == []
    with pytest.raises(FileNotFoundError):
        shared_memory.SharedMemory(name=names[0])
