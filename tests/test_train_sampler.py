"""PPO's rollout in the env workers (``sampler.py``): the same rollout the per-step loop would
collect -- the policy's distribution, SAME_STEP resets with the truncated step's value, the
reward normaliser replayed in step order -- and a training run through worker processes."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from jetbot_rt.train.device import to_cpu
from jetbot_rt.train.hyperparams import PPOArgs, ppo_args
from jetbot_rt.train.model import ActorCritic
from jetbot_rt.train.ppo import train
from jetbot_rt.train.sampler import PolicySampler, normalize_segment, stack_segments
from jetbot_rt.train.shared_steps import SharedSteps
from jetbot_rt.train.vec_env import EnvSpec, worker_env
from jetbot_rt.train.wrappers import normalize_rewards

pytest.importorskip("pybullet")


class Scripted(gym.Env):
    """Rewards from a list; terminates at the steps in ``ends``, truncates every ``limit``."""

    observation_space = gym.spaces.Box(0.0, 1.0, (1,))
    action_space = gym.spaces.Box(-1.0, 1.0, (1,))

    def __init__(self, rewards: np.ndarray, ends: set[int], limit: int) -> None:
        self.rewards, self.ends, self.limit = rewards, ends, limit
        self.t = self.since_reset = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.since_reset = 0
        return np.zeros(1, np.float32), {}

    def step(self, action):
        reward, t = float(self.rewards[self.t]), self.t
        self.t += 1
        self.since_reset += 1
        terminated = t in self.ends
        truncated = not terminated and self.since_reset >= self.limit
        return np.zeros(1, np.float32), reward, terminated, truncated, {}


def test_the_replayed_normaliser_is_the_vector_wrappers_step_by_step():
    steps, rng = 60, np.random.default_rng(0)
    rewards = rng.normal(0.0, 30.0, (steps, 2))
    scripts = [({7, 30}, 25), ({12}, 17)]

    def vector() -> SyncVectorEnv:
        return SyncVectorEnv([lambda r=rewards[:, i], s=s: Scripted(r, *s)
                              for i, s in enumerate(scripts)],
                             autoreset_mode=AutoresetMode.SAME_STEP)

    wrapped, normalizer = normalize_rewards(vector(), 0.99, 1.5)
    wrapped.reset(seed=0)
    want, terminated, truncated = [], [], []
    for _ in range(steps):
        _, reward, term, trunc, _ = wrapped.step(np.zeros((2, 1), np.float32))
        want.append(reward)
        terminated.append(term)
        truncated.append(trunc)
    terminated_a, truncated_a = np.array(terminated), np.array(truncated)
    assert terminated_a.any() and truncated_a.any()

    _, replayed = normalize_rewards(vector(), 0.99, 1.5)
    got = normalize_segment(replayed, 1.5, rewards, terminated_a, truncated_a)
    assert np.array_equal(got, np.array(want))
    assert np.abs(got).max() == 1.5  # the clip acted
    assert replayed.return_rms.var == normalizer.return_rms.var
    assert np.array_equal(replayed.accumulated_reward, normalizer.accumulated_reward)


@pytest.fixture(scope="module")
def sampler():
    args = ppo_args("forward")
    env = worker_env(EnvSpec("forward", args.config, args.shaping, 56, sampler=PolicySampler,
                             model=args.model), 1)
    env.reset(seed=3)
    yield env, args
    env.close()


def test_a_segment_is_the_policys_distribution_and_ends_episodes_as_the_vector_env(sampler):
    env, args = sampler
    torch.manual_seed(0)
    model = ActorCritic(args.model).eval()
    weights = to_cpu(model.state_dict())
    steps = env.unwrapped.task.episode_steps + 5  # one time-limit truncation
    segment = env.collect(weights, steps, (1, 1))
    assert segment["obs"].shape == (steps, 56, 56, 3) and segment["actions"].shape == (steps, 2)
    with torch.no_grad():
        mu, log_std, value = model(torch.from_numpy(segment["obs"]))
        normal = torch.distributions.Normal(mu, log_std.exp())
        logprob = normal.log_prob(torch.from_numpy(segment["actions"])).sum(-1)
    assert np.allclose(segment["values"], value[:, 0].numpy(), atol=1e-5)
    assert np.allclose(segment["logprobs"], logprob.numpy(), atol=1e-4)
    z = (segment["actions"] - mu.numpy()) / log_std.detach().exp().numpy()
    assert abs(z.mean()) < 0.2 and 0.85 < z.std() < 1.15  # unit normal noise
    last = steps - 6
    assert segment["truncated"].nonzero()[0].tolist() == [last]
    assert not segment["terminated"].any()
    assert segment["final_values"].nonzero()[0].tolist() == [last]
    assert [e[0] for e in segment["episodes"]] == [last]
    # The reset happened inside the truncating step: the next frame starts a new episode.
    assert not np.array_equal(segment["obs"][last + 1], segment["obs"][last])


def test_segments_are_seeded_by_run_update_and_env(sampler):
    env, args = sampler
    weights = to_cpu(ActorCritic(args.model).state_dict())
    noise = []
    for seed in ((1, 2), (1, 2), (1, 3)):
        env.reset(seed=5)
        segment = env.collect(weights, 4, seed)
        noise.append(segment["actions"])
    assert np.array_equal(noise[0], noise[1]) and not np.array_equal(noise[0], noise[2])
    stacked = stack_segments((segment, segment))
    assert stacked["actions"].shape == (4, 2, 2) and stacked["next_obs"].shape == (2, 56, 56, 3)


def test_a_worker_steps_until_the_workers_together_have_the_rollout(sampler):
    env, args = sampler
    weights = to_cpu(ActorCritic(args.model).state_dict())
    counters = SharedSteps.create(2)
    try:
        lengths = []
        for others in (20, 100, 0):
            share = counters.share(7, total=30, min_steps=5)
            counters.counts[share.bank, 0] = others  # what the other worker has taken
            segment = env.collect(weights, 50, (1, 7), share)
            lengths.append(len(segment["rewards"]))
            assert segment["obs"].shape[0] == segment["actions"].shape[0] == lengths[-1]
            assert counters.counts[share.bank, 1] == lengths[-1]
        assert lengths == [10, 5, 30]  # the rest of 30; its minimum; all of it alone
        share = counters.share(8, total=500, min_steps=5)
        assert len(env.collect(weights, 50, (1, 8), share)["rewards"]) == 50  # at most
    finally:
        counters.close()


def test_training_through_worker_processes_samples_in_them(tmp_path):
    args = PPOArgs(num_envs=2, num_steps=32, total_timesteps=128, out=str(tmp_path),
                   update_epochs=1, progress=False)
    assert args.workers is None and args.sample_in_workers
    summary = train(args)
    assert summary["global_step"] == 128 and summary["updates"] == 2
    assert (tmp_path / "policy.onnx").stat().st_size > 0
    # The weights went to the workers as plain bytes: a torch tensor is pickled as a file
    # descriptor served by this thread, whose traceback ended a Ctrl-C (a worker dying
    # mid-handover) in CI.
    from multiprocessing import resource_sharer
    assert resource_sharer._resource_sharer._listener is None, "weights sent as shared memory"
