"""PPO's asymmetric actor-critic (``jetbot-train train --critic state``): the critic reads the
task's privileged sim state, the actor -- and the exported ONNX -- the camera image alone;
both rollout sources carry the state and bootstrap from the critic; resume keeps the critic and
refuses a checkpoint of the other kind; a task without a critic state is refused."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from train_runner import train_main

from jetbot_rt.tasks.critic_state import COMMAND_NAMES
from jetbot_rt.tasks.seek import Seek
from jetbot_rt.train.checkpoint import load_checkpoint
from jetbot_rt.train.hyperparams import CriticConfig, ModelConfig, critic_config, ppo_args
from jetbot_rt.train.model import ActorCritic

pytest.importorskip("pybullet")

SIZE = 8
"""The frame's side: the smallest the network takes (the sim renders at it)."""
SMALL = ("--num-steps", "64", "--update-epochs", "1", "--num-minibatches", "2",
         "--num-envs", "1", "--workers", "0", "--model-image-size", str(SIZE), "--seed", "3",
         "--no-progress")
SEEK_PPO = ("train", "--task", "seek", "--algo", "ppo", *SMALL)
WIDTH = len(Seek.critic_state_names)
SHORT_SEEK = ("from jetbot_rt.tasks.seek import Seek\n\n\n"
              "class ShortSeek(Seek):\n    name = 'shortseek'\n    episode_steps = 16\n")
"""seek truncated after 16 steps: rollouts of 40 steps hold resets and truncations."""


def checkpoint(run: Path) -> dict:
    return torch.load(run / "checkpoint.pt", weights_only=True)


def steps(run: Path) -> list[str]:
    return [r.split(",")[1] for r in (run / "metrics.csv").read_text().splitlines()[1:]]


@pytest.fixture(scope="module")
def state_run(tmp_path_factory) -> Path:
    from jetbot_rt.train.cli import main

    out = tmp_path_factory.mktemp("asymmetric")
    assert main([*SEEK_PPO, "--critic", "state", "--timesteps", "128", "--out", str(out)]) == 0
    return out


def test_the_state_critic_trains_seek_and_exports_only_the_image_actor(state_run):
    assert steps(state_run) == ["64", "128"]
    state = checkpoint(state_run)
    assert state["critic"] == {"state_size": WIDTH, "hidden": 64}
    assert state["model"]["critic.0.weight"].shape == (64, WIDTH)  # the critic sees the state
    proto = onnx.load(state_run / "policy.onnx")
    assert [i.name for i in proto.graph.input] == ["obs"]  # one image in, nothing else
    assert [o.name for o in proto.graph.output] == ["mu", "log_std", "value"]
    assert not [i.name for i in proto.graph.initializer if "critic" in i.name]
    session = ort.InferenceSession(str(state_run / "policy.onnx"),
                                   providers=["CPUExecutionProvider"])
    assert session.get_inputs()[0].shape[1:] == [SIZE, SIZE, 3]
    images = np.random.default_rng(0).integers(0, 256, (4, SIZE, SIZE, 3)).astype(np.float32)
    mu = session.run(["mu"], {"obs": images})[0]
    actor = load_checkpoint(state_run / "checkpoint.pt").model()
    with torch.no_grad():
        want = actor(torch.from_numpy(images))[0].numpy()
    np.testing.assert_allclose(mu, want, atol=1e-5)


def test_the_critic_reads_the_tasks_privileged_state():
    from jetbot_rt.train.wrappers import Shaping, make_train_env

    env = make_train_env("seek", None, Shaping(), critic_state=True, image_size=(SIZE, SIZE))
    try:
        _, info = env.reset(seed=4)
        names = Seek.critic_state_names
        state = info["critic_state"]
        assert state.shape == (WIDTH,) and state.dtype == np.float32
        assert state[names.index("goal_distance")] == pytest.approx(info["distance"], abs=1e-6)
        assert not state[[names.index(n) for n in COMMAND_NAMES]].any()  # nothing sent yet
        _, _, _, _, info = env.step(np.array([0.8, 0.4], dtype=np.float32))
        commands = info["critic_state"][[names.index(n) for n in COMMAND_NAMES]]
        np.testing.assert_allclose(commands, [0.8, 0.4], atol=1e-6)
    finally:
        env.close()
    for task in ("forward", "follow", "avoid"):  # each built-in has one
        assert critic_config(ppo_args(task, {"critic": "state"})) is not None


@pytest.mark.parametrize("workers", [0, None], ids=["learner", "env-workers"])
def test_rollouts_carry_the_state_and_bootstrap_from_the_critic(tmp_path, workers):
    """Both rollout sources: the state is the one of each step's frame (a reset's frame has
    no command yet), every value is the critic's, and a truncated step's reward carries
    gamma times the critic's value of the final state (a critic that says 1000 everywhere
    makes those steps stand out of the clipped rewards)."""
    from jetbot_rt.train.rollout import make_rollout_source

    (tmp_path / "short.py").write_text(SHORT_SEEK)
    options = ppo_args(f"{tmp_path / 'short.py'}:ShortSeek", {
        "critic": "state", "num_envs": 2, "workers": workers, "num_steps": 40, "seed": 5,
        "model": {"image_size": SIZE}, "progress": False})
    torch.manual_seed(0)
    model = ActorCritic(options.model, critic_config(options))
    with torch.no_grad():
        model.critic[-1].weight.zero_()
        model.critic[-1].bias.fill_(1000.0)
    source = make_rollout_source(options, model, torch.device("cpu"))
    try:
        source.reset(model, [5, 6])
        rollout = source.collect(model, 1)
    finally:
        source.close(False)
    assert rollout.states.shape == (40, 2, WIDTH) and rollout.next_state.shape == (2, WIDTH)
    command = [Seek.critic_state_names.index(n) for n in COMMAND_NAMES]
    no_command = rollout.states[..., command].abs().sum(-1) == 0
    assert torch.equal(no_command[1:], rollout.dones[1:].bool())  # resets at 16 and 32
    assert rollout.dones.sum() == 4
    assert torch.allclose(rollout.values, torch.full_like(rollout.values, 1000.0))
    truncated = torch.nonzero(rollout.rewards > 500).tolist()
    assert truncated == [[15, 0], [15, 1], [31, 0], [31, 1]]


def test_resume_restores_the_critic_and_init_keeps_the_actor(state_run, tmp_path, capsys):
    from jetbot_rt.train.run_dir import starting_model

    run = tmp_path / "resumed"
    shutil.copytree(state_run, run)
    saved = load_checkpoint(run / "checkpoint.pt")
    options = ppo_args("seek", {"critic": "state", "model": {"image_size": SIZE}})
    model, resumed = starting_model(options, saved, "ppo", critic_config(options))
    assert resumed is not None and resumed.update == 2
    for name, weight in checkpoint(run)["model"].items():
        assert torch.equal(model.state_dict()[name], weight), name
    code, _, err = train_main(capsys, *SEEK_PPO, "--critic", "state", "--timesteps", "192",
                              "--resume", "--out", str(run))
    assert code == 0, err
    assert steps(run) == ["64", "128", "192"]
    assert checkpoint(run)["update"] == 3 and checkpoint(run)["critic"]["state_size"] == WIDTH
    # --init into an image-critic run: the actor, without the critic
    options = ppo_args("seek", {"init": str(state_run / "checkpoint.pt")})
    model, _ = starting_model(options, None, "ppo", critic_config(options))
    assert model.critic is None
    for name, weight in model.state_dict().items():
        assert torch.equal(weight, checkpoint(state_run)["model"][name]), name


def test_a_checkpoint_of_the_other_critic_is_refused_in_one_line(state_run, tmp_path, capsys):
    run = tmp_path / "state"
    shutil.copytree(state_run, run)
    before = (run / "metrics.csv").read_text()
    code, _, err = train_main(capsys, *SEEK_PPO, "--timesteps", "192", "--resume",
                              "--out", str(run))
    assert code == 2 and err.count("\n") == 1
    assert "was trained with --critic state, not --critic image" in err
    assert (run / "metrics.csv").read_text() == before  # refused before any training
    image = tmp_path / "image"
    code, _, err = train_main(capsys, *SEEK_PPO, "--timesteps", "64", "--out", str(image))
    assert code == 0, err
    code, _, err = train_main(capsys, *SEEK_PPO, "--critic", "state", "--timesteps", "128",
                              "--resume", "--out", str(image))
    assert code == 2 and err.count("\n") == 1
    assert "was trained with --critic image, not --critic state" in err
    # --init into a state-critic run: the image run's actor, a fresh critic
    from jetbot_rt.train.run_dir import starting_model

    options = ppo_args("seek", {"critic": "state", "init": str(image / "checkpoint.pt")})
    model, _ = starting_model(options, None, "ppo", critic_config(options))
    assert model.critic_config == CriticConfig(WIDTH)
    for name, weight in checkpoint(image)["model"].items():
        assert torch.equal(model.state_dict()[name], weight), name


def test_ctrl_c_saves_the_critic_and_exports_the_actor(tmp_path, capsys, monkeypatch):
    from jetbot_rt.train import ppo

    update = ppo._Run.update
    calls = []

    def interrupted_second(run: ppo._Run) -> dict:
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return update(run)

    monkeypatch.setattr(ppo._Run, "update", interrupted_second)
    code, _, err = train_main(capsys, *SEEK_PPO, "--critic", "state", "--timesteps", "640",
                              "--out", str(tmp_path))
    assert code == 130, err
    assert "--resume" in err
    state = checkpoint(tmp_path)
    assert state["update"] == 1 and state["critic"]["state_size"] == WIDTH
    assert [i.name for i in onnx.load(tmp_path / "policy.onnx").graph.input] == ["obs"]


def test_the_actor_starts_as_without_the_critic():
    """The critic is built last, so a seed gives the same first actor whichever critic: a
    run's policy differs from the image critic's only by what the critic taught it."""
    torch.manual_seed(7)
    image = ActorCritic(ModelConfig(image_size=SIZE))
    torch.manual_seed(7)
    state = ActorCritic(ModelConfig(image_size=SIZE), CriticConfig(WIDTH))
    assert image.state_dict().keys() == state.actor_state_dict().keys()
    assert sum(p.numel() for p in state.parameters()) == \
        ModelConfig(image_size=SIZE).parameter_count() + CriticConfig(WIDTH).parameter_count()
    for name, weight in image.state_dict().items():
        assert torch.equal(weight, state.actor_state_dict()[name]), name
    x = state.preprocess(torch.zeros(3, SIZE, SIZE, 3))
    with pytest.raises(ValueError, match="state"):
        state.value(x)
    assert state.value(x, torch.zeros(3, WIDTH)).shape == (3,)


@pytest.mark.parametrize(("args", "needle"), [
    (("--task", "TASKFILE", "--algo", "ppo", "--critic", "state"),
     "has no privileged critic state"),
    (("--task", "seek", "--algo", "ppo", "--critic", "pixels"),
     "--critic must be one of image, state, got 'pixels'"),
    (("--task", "seek", "--algo", "dagger", "--critic", "state"),
     "--critic is not an option of --algo dagger"),
])
def test_a_task_without_a_critic_state_or_a_bad_critic_is_one_line_and_exit_2(
        tmp_path, capsys, args, needle):
    task = tmp_path / "blind.py"
    task.write_text("from jetbot_rt.tasks import Task\n\n\nclass Blind(Task):\n"
                    "    name = 'blind'\n")
    args = tuple(f"{task}:Blind" if a == "TASKFILE" else a for a in args)
    code, _, err = train_main(capsys, "train", *args, "--out", str(tmp_path / "out"))
    assert code == 2 and err.count("\n") == 1 and needle in err, err
    assert not (tmp_path / "out" / "checkpoint.pt").exists()
