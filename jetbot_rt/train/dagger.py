"""DAgger (Ross et al. 2011): train the camera policy by imitating a privileged teacher.

The teacher (``expert.py``) reads the simulator's state; the student is the network PPO
trains (``model.ActorCritic``, the same preprocessing and ONNX export), and sees only the
camera. Iteration 0 lets the teacher drive (with action noise, for states off its own path);
every later one lets the student drive (the teacher drives a ``beta`` share of the episodes,
``beta`` halving each iteration) and labels every frame the student saw with the teacher's
action. The frames are aggregated (uint8) and the student's ``mu`` is regressed onto the
labels (MSE, Adam) for a few epochs. A training-time privilege only: the exported policy
needs nothing but the image. docs/TRAINING.md ("Training seek by DAgger") says why.
"""

from __future__ import annotations

import csv
import time
from dataclasses import asdict
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv, VectorEnv
from tqdm import tqdm

from jetbot_rt.errors import UsageError
from jetbot_rt.train.args import DAggerArgs, dagger_args
from jetbot_rt.train.checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint
from jetbot_rt.train.dagger_sampler import LabelSampler
from jetbot_rt.train.env import get_task, max_speed_of
from jetbot_rt.train.expert import Expert
from jetbot_rt.train.export import export_model
from jetbot_rt.train.model import ActorCritic, ModelConfig
from jetbot_rt.train.ppo import (
    CURVE_NAME,
    METRICS_NAME,
    POLICY_NAME,
    Interrupted,
    _close,
    _prepare_out,
    _worker_env,
    _write_metrics_row,
)
from jetbot_rt.train.wrappers import Shaping

METRIC_FIELDS = ("iteration", "global_step", "wall_s", "collect_s", "regress_s", "dataset",
                 "beta", "episodes", "success_rate", "expert_success_rate", "loss")
NO_SHAPING = Shaping("none", 0.0, 0.0, 0.0, 0.0)
EXPERT_INFO = ("pose", "goal_xy", "speed", "is_success")
"""The info keys DAgger reads: the expert's inputs, and the outcome of an episode."""


class Dataset:
    """The aggregated frames (uint8, as rendered) and the expert's labels, growing."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        self.frames = np.zeros((0, *shape), dtype=np.uint8)
        self.labels = np.zeros((0, 2), dtype=np.float32)

    def add(self, frames: np.ndarray, labels: np.ndarray) -> None:
        if len(frames):
            self.frames = np.concatenate([self.frames, frames])
            self.labels = np.concatenate([self.labels, labels])

    def __len__(self) -> int:
        return len(self.labels)


def jitter(x: torch.Tensor, amount: float, rng: np.random.Generator) -> torch.Tensor:
    """``x`` (preprocessed, 0..1) with per-frame brightness, contrast (about the frame's mean)
    and colour-channel gains drawn from 1 +- ``amount`` (channels 1 +- ``amount`` / 2)."""
    n = x.shape[0]

    def factors(size: tuple[int, ...], spread: float) -> torch.Tensor:
        return torch.from_numpy(rng.uniform(1 - spread, 1 + spread, size).astype(np.float32))

    brightness, contrast = factors((n, 1, 1, 1), amount), factors((n, 1, 1, 1), amount)
    channels = factors((n, 3, 1, 1), amount / 2)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    return (((x - mean) * contrast + mean) * brightness * channels).clamp(0.0, 1.0)


def regress(model: ActorCritic, optimizer: torch.optim.Optimizer, data: Dataset,
            args: DAggerArgs, rng: np.random.Generator) -> float:
    """Weighted MSE of ``mu`` onto the labels over ``args.train_samples`` frames; the mean
    loss."""
    model.train()
    losses: list[float] = []
    stop = np.all(data.labels <= 0.0, axis=1)  # stop or back off
    weights = torch.from_numpy(np.where(stop, args.stop_weight, 1.0).astype(np.float32))
    passes = -(-args.train_samples // max(len(data), 1))
    order = np.concatenate([rng.permutation(len(data)) for _ in range(passes)])
    for begin in range(0, args.train_samples, args.batch_size):
        idx = np.sort(order[begin:min(begin + args.batch_size, args.train_samples)])
        x = model.preprocess(torch.from_numpy(data.frames[idx]))
        if args.photometric_jitter > 0:
            x = jitter(x, args.photometric_jitter, rng)
        mu = model.heads(x)[0]
        error = ((mu - torch.from_numpy(data.labels[idx])) ** 2).sum(-1)
        loss = (error * weights[idx]).sum() / weights[idx].sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    model.eval()
    return float(np.mean(losses)) if losses else float("nan")


def collect(envs: VectorEnv, model: ActorCritic, expert: Expert, data: Dataset,
            args: DAggerArgs, iteration: int, bar: tqdm) -> dict[str, Any]:
    """Roll out one iteration in the env workers (``dagger_sampler``); add every frame of
    their finished episodes with its label."""
    beta = 1.0 if iteration == 0 else args.beta * 0.5 ** (iteration - 1)
    n = envs.num_envs
    # numpy, not tensors (see ppo.py): plain bytes through the pipes
    weights = {name: w.detach().numpy().copy() for name, w in model.state_dict().items()}
    results = envs.unwrapped.call(
        "collect_labelled", weights, -(-args.steps_per_iteration // n),
        (args.seed, iteration), beta, args.expert_noise, expert)
    outcomes: dict[bool, list[float]] = {True: [], False: []}
    steps = 0
    for result in results:
        data.add(result["frames"], result["labels"])
        steps += len(result["labels"])
        for by_expert, success in result["outcomes"]:
            outcomes[by_expert].append(float(success))
    bar.update(steps)
    student, teacher = outcomes[False], outcomes[True]
    return {"beta": round(beta, 4), "episodes": len(student) + len(teacher), "steps": steps,
            "success_rate": round(float(np.mean(student)), 3) if student else "",
            "expert_success_rate": round(float(np.mean(teacher)), 3) if teacher else ""}


def learning_rate_at(args: DAggerArgs, iteration: int) -> float:
    """The step size of the regression after rollout ``iteration`` (0-based)."""
    if args.final_learning_rate is None or args.iterations <= 1:
        return args.learning_rate
    ratio = args.final_learning_rate / args.learning_rate
    return args.learning_rate * ratio ** (min(iteration, args.iterations - 1)
                                          / (args.iterations - 1))


def _labelling_env(task: str, config: Any, image_size: int, model: ModelConfig,
                   index: int) -> LabelSampler:
    """Built inside each worker (see ``ppo._worker_env``)."""
    return LabelSampler(_worker_env(task, config, NO_SHAPING, image_size, keep=EXPERT_INFO),
                        model, index)


def make_envs(args: DAggerArgs, model: ModelConfig) -> VectorEnv:
    factories = [partial(_labelling_env, args.task, args.config, model.image_size, model, j)
                 for j in range(args.num_envs)]
    if args.workers == 0:
        return SyncVectorEnv(factories, autoreset_mode=AutoresetMode.SAME_STEP)
    return AsyncVectorEnv(factories, context="spawn", autoreset_mode=AutoresetMode.SAME_STEP,
                          shared_memory=True)


def plot_curve(metrics_csv: Path, png: Path) -> None:
    """Student success per iteration (its own rollouts) and the regression loss."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with metrics_csv.open() as handle:
        rows = list(csv.DictReader(handle))
    fig, (ax_succ, ax_loss) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    done = [r for r in rows if r["success_rate"]]
    ax_succ.plot([int(r["global_step"]) for r in done],
                 [float(r["success_rate"]) for r in done], "o-", color="tab:green",
                 label="student drives")
    ax_succ.set_ylim(-0.05, 1.05)
    ax_succ.set_ylabel("success rate (rollouts)")
    ax_succ.legend(loc="lower right")
    ax_loss.plot([int(r["global_step"]) for r in rows], [float(r["loss"]) for r in rows], "o-")
    ax_loss.set_yscale("log")
    ax_loss.set_ylabel("imitation loss (MSE)")
    ax_loss.set_xlabel("environment steps")
    fig.suptitle("jetbot-train DAgger learning curve")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def train(args: DAggerArgs) -> dict[str, Any]:
    """Run DAgger; writes checkpoint, ONNX, metrics and curve to ``args.out``; returns a
    summary. Ctrl-C: writes them as they are and raises ``Interrupted``."""
    if args.task != "seek":
        raise UsageError(f"--algo dagger has an expert for task seek only, not {args.task!r}")
    if args.num_envs <= 0:
        raise UsageError(f"--num-envs must be > 0, got {args.num_envs}")
    if args.workers not in (None, 0, args.num_envs):
        raise UsageError(f"--workers must be 0 or --num-envs ({args.num_envs}), got "
                         f"{args.workers}")
    out = Path(args.out)
    _prepare_out(out)
    checkpoint_path, metrics_path = out / CHECKPOINT_NAME, out / METRICS_NAME
    torch.manual_seed(args.seed)
    model = ActorCritic(args.model)
    if args.init:
        model = load_checkpoint(args.init).model()
    optimizer = torch.optim.Adam(model.parameters(), lr=args.learning_rate)
    iteration, global_step, wall_before = 0, 0, 0.0
    if args.resume and checkpoint_path.exists():
        saved = load_checkpoint(checkpoint_path)
        resume_state = saved.check_resumable(args.task, "dagger")
        model = saved.model()
        optimizer = torch.optim.Adam(model.parameters(), lr=args.learning_rate)
        saved.load_optimizer(optimizer)
        iteration, global_step, wall_before = (resume_state.update, resume_state.global_step,
                                               resume_state.wall_s)
    elif metrics_path.exists():
        metrics_path.unlink()
    model.eval()
    rng = np.random.default_rng(args.seed + iteration)
    max_speed = max_speed_of(args.config, get_task(args.task))
    expert = Expert(stop_distance=args.stop_distance, min_forward=args.min_forward,
                    search_left=args.search_left, search_right=args.search_right,
                    backoff_distance=args.backoff_distance)
    start = time.perf_counter()
    total = args.iterations * args.steps_per_iteration
    bar = tqdm(total=total, initial=min(global_step, total), disable=not args.progress,
               unit="step", dynamic_ncols=True)
    interrupted = False
    envs: VectorEnv | None = None

    def save() -> None:
        save_checkpoint(checkpoint_path, {
            "task": args.task, "algo": "dagger", "model": model.state_dict(),
            "model_config": model.config.to_dict(), "optimizer": optimizer.state_dict(),
            "global_step": global_step, "update": iteration,
            "wall_s": wall_before + time.perf_counter() - start, "max_speed": max_speed,
            "args": {k: v for k, v in asdict(args).items() if k not in ("config", "model")},
        })

    try:  # from the workers' start on, Ctrl-C saves and prints the --resume command
        envs = make_envs(args, model.config)
        data = Dataset(envs.single_observation_space.shape)
        while iteration < args.iterations:
            torch.set_num_threads(1)
            began = time.perf_counter()
            row = collect(envs, model, expert, data, args, iteration, bar)
            global_step += row.pop("steps")
            torch.set_num_threads(args.torch_threads)
            for group in optimizer.param_groups:
                group["lr"] = learning_rate_at(args, iteration)
            collected = time.perf_counter()
            loss = regress(model, optimizer, data, args, rng)
            iteration += 1
            row.update(iteration=iteration, global_step=global_step, dataset=len(data),
                       loss=round(loss, 5), collect_s=round(collected - began, 1),
                       regress_s=round(time.perf_counter() - collected, 1),
                       wall_s=round(wall_before + time.perf_counter() - start, 1))
            _write_metrics_row(metrics_path, row, METRIC_FIELDS)
            if args.snapshots and iteration % args.snapshots == 0:
                export_model(model.eval(), out / f"policy_{iteration}.onnx", task=args.task,
                             max_speed=max_speed)
            bar.set_postfix(succ=row["success_rate"], loss=row["loss"], refresh=False)
            save()
    except KeyboardInterrupt:
        interrupted = True
        save()
    finally:
        bar.close()
        # After Ctrl-C the workers are ended, not waited for: a whole iteration's
        # collection is one call to them, and close() would wait for it to finish.
        if envs is not None:
            _close(envs, interrupted)
    export_model(model.eval(), out / POLICY_NAME, task=args.task, max_speed=max_speed)
    if metrics_path.exists():
        plot_curve(metrics_path, out / CURVE_NAME)
    wall = wall_before + time.perf_counter() - start
    summary = {"global_step": global_step, "updates": iteration, "wall_s": wall,
               "steps_per_s": round(global_step / max(wall, 1e-9), 1),
               "checkpoint": str(checkpoint_path), "policy": str(out / POLICY_NAME)}
    if interrupted:
        raise Interrupted(summary)
    return summary


__all__ = ["DAggerArgs", "Dataset", "dagger_args", "regress", "train"]
