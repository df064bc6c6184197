"""The learner on a GPU (``--device cuda``): PPO's update (``--overlap``'s too) and DAgger's
regression on CUDA learn what they learn on the CPU, from the same frames, and write CPU
checkpoints. Skipped without CUDA (CI has none); run on a GPU host with
``pytest tests/test_train_cuda.py``."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from plain_sim import plain_sim_file
from train_runner import train_here

pytest.importorskip("pybullet")
pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")

PPO_ONE_UPDATE = ("train", "--task", "forward", "--algo", "ppo", "--timesteps", "64",
                  "--num-steps", "64", "--num-envs", "1", "--update-epochs", "2",
                  "--num-minibatches", "2", "--seed", "5", "--no-progress")
"""One rollout, sampled by the env worker's onnxruntime copy from its own seeded generator
(the same actions whichever device the learner is on), and one update."""
PPO_OVERLAPPED = ("train", "--task", "forward", "--algo", "ppo", "--timesteps", "128",
                  "--num-steps", "64", "--num-envs", "1", "--update-epochs", "2",
                  "--num-minibatches", "2", "--seed", "5", "--no-progress", "--overlap")
"""Two rollouts with ``--overlap``: the second collected with the first weights during the
first update (the same actions on either device), the second update from the learner's view
of it (log-probabilities and values recomputed on the learner's device)."""
DAGGER_ONE_ITERATION = ("train", "--task", "seek", "--algo", "dagger", "--iterations", "1",
                        "--steps-per-iteration", "40", "--train-samples", "256",
                        "--num-envs", "1", "--seed", "5", "--no-progress")
"""Iteration 0: the expert drives (the same frames and labels on either device), then one
regression."""


def _trained(capsys: pytest.CaptureFixture[str], out: Path, args: tuple[str, ...],
             device: str) -> dict[str, torch.Tensor]:
    out.parent.mkdir(parents=True)
    result = train_here(capsys, *args, "--device", device, "--out", str(out),
                        "--config", str(plain_sim_file(out.parent)))
    assert result.returncode == 0, result.stderr
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert state["args"]["device"] == device
    weights = state["model"]
    assert all(t.device.type == "cpu" for t in weights.values())  # resumes on any machine
    assert (out / "policy.onnx").stat().st_size > 0
    return weights


def _initial(seed: int, task: str, algo: str) -> dict[str, torch.Tensor]:
    """The network as a run of ``seed`` starts it (the trainers seed torch, then build it)."""
    from jetbot_rt.train import hyperparams
    from jetbot_rt.train.model import ActorCritic

    torch.manual_seed(seed)
    return ActorCritic(getattr(hyperparams, f"{algo}_args")(task, {}).model).state_dict()


def _same_learning(cpu: dict[str, torch.Tensor], cuda: dict[str, torch.Tensor],
                   start: dict[str, torch.Tensor], learned: tuple[str, ...]) -> None:
    """The two devices moved each layer the same way: the moves' cosine near 1 and their sizes
    within 10 % (float round-off and TF32 convolutions on the GPU, not a different update).
    Not element by element: Adam's first steps move a weight of a near-zero gradient by the
    full step size, whose sign round-off decides."""
    for name in learned:
        on_cpu, on_cuda = (cpu[name] - start[name]).flatten(), (cuda[name] - start[name]).flatten()
        cosine = torch.nn.functional.cosine_similarity(on_cpu, on_cuda, dim=0).item()
        ratio = (on_cuda.norm() / on_cpu.norm()).item()
        assert on_cpu.norm() > 0, name
        assert cosine > 0.95 and 0.9 < ratio < 1.1, (name, cosine, ratio)


@pytest.mark.parametrize("args", [PPO_ONE_UPDATE, PPO_OVERLAPPED], ids=["sync", "overlap"])
def test_ppo_update_on_cuda_learns_what_the_cpu_learns(tmp_path, capsys, args):
    cpu = _trained(capsys, tmp_path / "cpu" / "run", args, "cpu")
    cuda = _trained(capsys, tmp_path / "cuda" / "run", args, "cuda")
    start = _initial(5, "forward", "ppo")
    assert cpu.keys() == cuda.keys() == start.keys()
    _same_learning(cpu, cuda, start, ("mu_head.weight", "value_head.weight", "encoder.0.weight"))


def test_dagger_regression_on_cuda_learns_what_the_cpu_learns(tmp_path, capsys):
    cpu = _trained(capsys, tmp_path / "cpu" / "run", DAGGER_ONE_ITERATION, "cpu")
    cuda = _trained(capsys, tmp_path / "cuda" / "run", DAGGER_ONE_ITERATION, "cuda")
    start = _initial(5, "seek", "dagger")
    _same_learning(cpu, cuda, start, ("mu_head.weight", "encoder.0.weight"))
