"""DAgger's rollouts in the env workers (``dagger_sampler.py``): the frames are the ones the
driver saw, each labelled with the expert's action on that state; the student drives with
its network's ``mu``; an iteration is reproducible from its seed. In the plain sim (pinhole,
no appearance families: ``plain_sim``), which the sampler's bookkeeping does not depend on
(the looks' own replay is test_appearance_families.py's): 11 s -> 6 s."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plain_sim import plain_config

from jetbot_rt.train.dagger import labelling_spec
from jetbot_rt.train.expert import Expert
from jetbot_rt.train.hyperparams import ModelConfig
from jetbot_rt.train.model import ActorCritic
from jetbot_rt.train.vec_env import worker_env

pytest.importorskip("pybullet")

MODEL = ModelConfig()


def weights_of(model: ActorCritic) -> dict[str, np.ndarray]:
    return {name: w.detach().numpy().copy() for name, w in model.state_dict().items()}


@pytest.fixture(scope="module")
def sampler():
    env = worker_env(labelling_spec("seek", plain_config(), MODEL), 1)
    yield env
    env.close()


def test_the_expert_drives_with_beta_1_and_every_frame_carries_its_label(sampler):
    expert = Expert()
    model = ActorCritic(MODEL)
    result = sampler.collect_labelled(weights_of(model), 200, (3, 2), 1.0, 0.0, expert)
    frames, labels = result["frames"], result["labels"]
    assert len(frames) == len(labels) >= 200 and frames.dtype == np.uint8
    assert all(by_expert for by_expert, _ in result["outcomes"])
    assert sum(success for _, success in result["outcomes"]) >= len(result["outcomes"]) - 1
    # the same scene replayed by hand: the frames and the expert's labels on them
    env = sampler.env
    obs, info = env.reset(seed=3 * 100_000 + 2 * 1000 + 1)
    for t in range(60):
        label = expert.act(info["pose"], info["goal_xy"], float(info["speed"]))
        np.testing.assert_array_equal(frames[t], obs)
        np.testing.assert_allclose(labels[t], label)
        obs, _, terminated, truncated, info = env.step(label)
        assert not (terminated or truncated)
    assert len({frames[t].tobytes() for t in range(60)}) > 50, "one buffer kept"
    assert len(result["symmetric"]) == len(labels) and not result["symmetric"].any()


class SidedExpert(Expert):
    """seek's expert, called symmetric where its label turns right: a flag the test can
    recompute from the labels, so each frame's flag is shown to be of that frame's state."""

    def symmetric(self, info):
        return bool(np.subtract(*self.label(info)) > 0)


def test_each_frame_carries_the_experts_symmetric_on_its_state(sampler):
    result = sampler.collect_labelled(weights_of(ActorCritic(MODEL)), 150, (6, 1), 1.0, 0.2,
                                      SidedExpert())
    labels, symmetric = result["labels"], result["symmetric"]
    assert symmetric.dtype == bool and len(symmetric) == len(labels)
    np.testing.assert_array_equal(symmetric, labels[:, 0] > labels[:, 1])
    assert symmetric.any() and not symmetric.all()


def test_the_student_drives_with_beta_0_on_its_networks_mu(sampler):
    torch.manual_seed(0)
    model = ActorCritic(MODEL).eval()
    with torch.no_grad():  # a student that turns: its actions show in the frames
        model.mu_head.bias[:] = torch.tensor([-0.6, 0.6])
    result = sampler.collect_labelled(weights_of(model), 50, (4, 1), 0.0, 0.3, Expert())
    assert not any(by_expert for by_expert, _ in result["outcomes"])
    env = sampler.env
    obs, _ = env.reset(seed=4 * 100_000 + 1 * 1000 + 1)
    for t in range(30):
        np.testing.assert_array_equal(result["frames"][t], obs)
        with torch.no_grad():
            mu = model(torch.from_numpy(obs[None]))[0][0].numpy()
        obs, *_ = env.step(np.clip(mu, -1, 1))


def test_an_iteration_is_reproducible_from_its_seed(sampler):
    weights = weights_of(ActorCritic(MODEL))
    first, again, other = (sampler.collect_labelled(weights, 100, seed, 0.5, 0.3, Expert())
                           for seed in ((5, 3), (5, 3), (5, 4)))
    np.testing.assert_array_equal(first["frames"], again["frames"])
    np.testing.assert_array_equal(first["labels"], again["labels"])
    assert first["outcomes"] == again["outcomes"]
    assert first["frames"].shape != other["frames"].shape or not np.array_equal(
        first["frames"], other["frames"])
