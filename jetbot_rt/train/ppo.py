"""PPO for the camera-image JetBot tasks, readable top to bottom (after cleanrl's
``ppo_continuous_action.py``).

One PyBullet client per worker process (``AsyncVectorEnv``), or all envs in the learner's
process (``SyncVectorEnv``, ``workers=0``). With worker processes the workers also run the
policy, a whole rollout at a time (``sampler.py``, ``sample_in_workers``); otherwise the loop
below computes every step's actions here. Gymnasium 1.x vector envs autoreset in the *next*
step by default, which would put a reset observation paired with an ignored action into the
rollout; we ask for SAME_STEP autoreset and bootstrap the time-limit truncation from the final
observation's value.
The reward the learner sees is built by wrappers (``wrappers.py``): shaping per env,
normalisation and clipping over the vector env.
"""

from __future__ import annotations

import csv
import math
import multiprocessing
import signal
import time
from collections import deque
from dataclasses import asdict
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv, VectorEnv
from tqdm import tqdm

from jetbot_rt.config import Config
from jetbot_rt.errors import UsageError
from jetbot_rt.train.args import TASK_DEFAULTS, PPOArgs, ppo_args, usable_cores
from jetbot_rt.train.checkpoint import (
    CHECKPOINT_NAME,
    TrainingState,
    load_checkpoint,
    save_checkpoint,
)
from jetbot_rt.train.device import resolve_device, to_cpu
from jetbot_rt.train.env import get_task, max_speed_of
from jetbot_rt.train.export import export_model
from jetbot_rt.train.model import ActorCritic, ModelConfig, normal_log_prob
from jetbot_rt.train.ray_workers import WorkersLost
from jetbot_rt.train.sampler import PolicySampler, normalize_segment, stack_segments
from jetbot_rt.train.wrappers import KeepInfo, Shaping, make_train_env, normalize_rewards

METRICS_NAME = "metrics.csv"
CURVE_NAME = "learning_curve.png"
POLICY_NAME = "policy.onnx"
METRIC_FIELDS = (
    "update", "global_step", "wall_s", "steps_per_s", "episodes", "mean_return",
    "mean_final_distance", "success_rate", "policy_loss", "value_loss", "entropy",
    "approx_kl", "clipfrac", "learning_rate", "reward_scale", "worker_restarts",
)


EPISODE_INFO = ("episode", "distance", "is_success")
"""The only ``info`` keys the learner reads (at an episode's end); the workers drop the rest."""


class Interrupted(Exception):
    """Ctrl-C during training; the checkpoint, curve and policy were written."""

    def __init__(self, summary: dict[str, Any]) -> None:
        super().__init__("interrupted")
        self.summary = summary


def _write_metrics_row(path: Path, row: dict[str, Any],
                       names: tuple[str, ...] = METRIC_FIELDS) -> None:
    new = not path.exists()
    with path.open("a", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=names)
        if new:
            writer.writeheader()
        writer.writerow({k: row.get(k, "") for k in names})


def plot_learning_curve(metrics_csv: Path, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with metrics_csv.open() as handle:
        rows = [r for r in csv.DictReader(handle) if r["mean_return"]]
    steps = [int(r["global_step"]) for r in rows]
    fig, (ax_ret, ax_succ) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    ax_ret.plot(steps, [float(r["mean_return"]) for r in rows])
    if rows:
        ax_ret.set_yscale("symlog", linthresh=1e4)
    else:
        ax_ret.text(0.5, 0.5, "no episode finished yet", ha="center", transform=ax_ret.transAxes)
    ax_ret.set_ylabel("mean episode return")
    ax_succ.plot(steps, [float(r["success_rate"]) for r in rows], color="tab:green")
    ax_succ.set_ylim(-0.05, 1.05)
    ax_succ.set_ylabel("training success rate")
    ax_succ.set_xlabel("environment steps")
    fig.suptitle("jetbot-train PPO learning curve")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _prepare_out(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write_test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UsageError(f"cannot write to output directory {out}: {exc.strerror or exc}") from None


def _worker_env(task: str, config: Config, shaping: Shaping, image_size: int,
                sampler: ModelConfig | None = None, index: int = 0,
                keep: tuple[str, ...] = EPISODE_INFO) -> Any:
    """Built inside each worker: Ctrl-C is the learner's to handle (it saves a checkpoint
    and then closes the workers), not a traceback from every worker. ``sampler``: the
    network of a ``PolicySampler`` around the env (env ``index``); ``keep``: the info keys
    the trainer reads."""
    if multiprocessing.parent_process() is not None:  # AsyncVectorEnv also calls it here
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    env = KeepInfo(make_train_env(task, config, shaping, image_size=(image_size, image_size)),
                   keep)
    return env if sampler is None else PolicySampler(env, sampler, index)


def _close(envs: VectorEnv, interrupted: bool) -> None:
    """Close the env workers. Ctrl-C can stop the learner half-way through reading a worker's
    message (with ``sample_in_workers`` it waits in that read for most of a rollout): the rest
    in the pipe cannot be read, and gymnasium's close would read it (seen: EOFError, exit 1
    instead of 130). After Ctrl-C the worker processes are ended and nothing more is read."""
    vector = envs.unwrapped
    if not (interrupted and isinstance(vector, AsyncVectorEnv)):
        envs.close()
        return
    for process in vector.processes:
        process.terminate()
    for process in vector.processes:
        process.join()
    for pipe in vector.parent_pipes:
        pipe.close()
    vector.closed = True  # its __del__ would try again


def samples_in_workers(args: PPOArgs) -> bool:
    """Whether the env workers run the policy through whole rollouts (``sampler.py``)."""
    return args.sample_in_workers and args.ray is None and args.workers != 0


def make_vector_env(args: PPOArgs, model: ModelConfig) -> tuple[VectorEnv, Any]:
    """SAME_STEP autoreset either way (module docstring); the reward normaliser with it."""
    sampler = model if samples_in_workers(args) else None
    factories = [partial(_worker_env, args.task, args.config, args.shaping, model.image_size,
                         sampler, i) for i in range(args.num_envs)]
    envs: VectorEnv
    if args.ray is not None:
        from jetbot_rt.train.ray_workers import RayVectorEnv

        envs = RayVectorEnv(factories, address=args.ray, workers=args.workers,
                            max_restarts=args.ray_max_restarts)
        return normalize_rewards(envs, args.gamma, args.reward_clip)
    if args.workers == 0:
        envs = SyncVectorEnv(factories, autoreset_mode=AutoresetMode.SAME_STEP)
    else:
        envs = AsyncVectorEnv(factories, context="spawn", autoreset_mode=AutoresetMode.SAME_STEP,
                              shared_memory=True)
    return normalize_rewards(envs, args.gamma, args.reward_clip)


def _tensorboard(out: Path) -> Any:
    """A SummaryWriter into ``out`` when the ``tensorboard`` extra is installed, else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out))


def _rms_state(rms: Any) -> dict[str, float]:
    return {"mean": float(rms.mean), "var": float(rms.var), "count": float(rms.count)}


def _load_rms(rms: Any, state: dict[str, float]) -> None:
    rms.mean, rms.var, rms.count = (np.float64(state["mean"]), np.float64(state["var"]),
                                    float(state["count"]))


def train(args: PPOArgs) -> dict[str, Any]:
    """Run PPO; writes checkpoint, ONNX, metrics and curve to ``args.out``; returns a summary.
    Ctrl-C: writes them as they are and raises ``Interrupted`` (with the summary)."""
    if args.total_timesteps <= 0:
        raise UsageError(f"--total-timesteps must be > 0, got {args.total_timesteps}")
    if args.num_envs <= 0:
        raise UsageError(f"--num-envs must be > 0, got {args.num_envs}")
    if args.ray is not None and args.workers is not None and not 0 < args.workers <= args.num_envs:
        raise UsageError(f"--workers with --ray must be 1 .. --num-envs ({args.num_envs}), "
                         f"got {args.workers}")
    if args.ray is None and args.workers not in (None, 0, args.num_envs):
        raise UsageError(f"--workers must be 0 (envs in this process) or --num-envs "
                         f"({args.num_envs}, one process each), got {args.workers}")
    if args.ray_max_restarts < 0:
        raise UsageError(f"--ray-max-restarts must be >= 0, got {args.ray_max_restarts}")
    get_task(args.task)
    _ = args.shaping  # validates reward_transform before any worker starts
    device = resolve_device(args.device)
    out = Path(args.out)
    _prepare_out(out)
    checkpoint_path = out / CHECKPOINT_NAME
    metrics_path = out / METRICS_NAME

    torch.manual_seed(args.seed)
    torch.set_num_threads(args.torch_threads)
    rng = np.random.default_rng(args.seed)
    model = ActorCritic(args.model)
    if args.init:
        model = load_checkpoint(args.init).model().train()
    model.to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=args.learning_rate, eps=1e-5)
    global_step, update, wall_before = 0, 0, 0.0
    resume_state: TrainingState | None = None
    if args.resume and checkpoint_path.exists():
        saved = load_checkpoint(checkpoint_path)
        resume_state = saved.check_resumable(args.task, "ppo")
        model = saved.model().train().to(device)
        optimizer = torch.optim.Adam(model.parameters(), lr=args.learning_rate, eps=1e-5)
        saved.load_optimizer(optimizer)
        global_step, update = resume_state.global_step, resume_state.update
        wall_before = resume_state.wall_s
        rng = np.random.default_rng(args.seed + update)
    elif not args.resume and metrics_path.exists():
        metrics_path.unlink()

    batch_size = args.num_envs * args.num_steps
    minibatch_size = max(1, batch_size // args.num_minibatches)
    num_updates = math.ceil(args.total_timesteps / batch_size)
    max_speed = max_speed_of(args.config, get_task(args.task))

    envs, normalizer = make_vector_env(args, model.config)
    if resume_state is not None and resume_state.reward_rms is not None:
        _load_rms(normalizer.return_rms, resume_state.reward_rms)
    writer = _tensorboard(out)
    with torch.no_grad():
        frame = torch.zeros((1, *envs.single_observation_space.shape))
        obs_shape = model.preprocess(frame).shape[1:]
    obs_buf = torch.zeros((args.num_steps, args.num_envs, *obs_shape), device=device)
    actions_buf = torch.zeros((args.num_steps, args.num_envs, 2), device=device)
    logprobs_buf = torch.zeros((args.num_steps, args.num_envs), device=device)
    rewards_buf = torch.zeros((args.num_steps, args.num_envs), device=device)
    dones_buf = torch.zeros((args.num_steps, args.num_envs), device=device)
    values_buf = torch.zeros((args.num_steps, args.num_envs), device=device)

    recent_returns: deque[float] = deque(maxlen=20)
    recent_distances: deque[float] = deque(maxlen=20)
    recent_success: deque[float] = deque(maxlen=20)
    episodes = 0

    sampling = samples_in_workers(args)
    seeds = [args.seed + update * 1000 + i for i in range(args.num_envs)]
    next_obs_np, _ = envs.reset(seed=seeds)
    next_obs = model.preprocess(torch.from_numpy(next_obs_np).to(device))
    next_done = torch.zeros(args.num_envs, device=device)
    start = time.perf_counter()
    start_step = global_step
    bar = tqdm(total=args.total_timesteps, initial=min(global_step, args.total_timesteps),
               disable=not args.progress, unit="step", dynamic_ncols=True)
    row: dict[str, Any] = {}
    interrupted = False
    lost: WorkersLost | None = None

    def save() -> None:
        _save(checkpoint_path, args, model, optimizer, normalizer.return_rms, global_step,
              update, wall_before + time.perf_counter() - start, max_speed)

    try:
        while global_step < args.total_timesteps:
            update += 1
            if args.anneal_lr:
                frac = max(0.0, 1.0 - global_step / args.total_timesteps)
                optimizer.param_groups[0]["lr"] = frac * args.learning_rate

            if sampling:  # the workers run the policy through the whole rollout
                # numpy, not tensors: torch pickles a tensor as a shared-memory file descriptor
                # handed over by a resource_sharer thread, which printed a traceback when a
                # worker died on Ctrl-C mid-handover.
                weights = {name: w.numpy() for name, w in to_cpu(model.state_dict()).items()}
                segment = stack_segments(envs.unwrapped.call(
                    "collect", weights, args.num_steps, (args.seed, update)))
                global_step += args.num_steps * args.num_envs
                frames = torch.from_numpy(segment["obs"]).to(device)
                obs_buf[:] = model.preprocess(frames.flatten(0, 1)).reshape(obs_buf.shape)
                for buf, key in ((actions_buf, "actions"), (logprobs_buf, "logprobs"),
                                 (values_buf, "values")):
                    buf[:] = torch.from_numpy(segment[key]).to(device)
                done = segment["terminated"] | segment["truncated"]
                dones_buf[0] = next_done
                dones_buf[1:] = torch.from_numpy(done[:-1]).to(device)
                reward = normalize_segment(normalizer, args.reward_clip, segment["rewards"],
                                           segment["terminated"], segment["truncated"])
                # final_values: the truncated steps' (see below), 0 elsewhere.
                reward += args.gamma * segment["final_values"]
                rewards_buf[:] = torch.as_tensor(reward, dtype=torch.float32, device=device)
                for _, _, episode_return, distance, success in segment["episodes"]:
                    recent_returns.append(episode_return)
                    recent_distances.append(distance)
                    recent_success.append(success)
                    episodes += 1
                next_obs = model.preprocess(torch.from_numpy(segment["next_obs"]).to(device))
                next_done = torch.as_tensor(done[-1], dtype=torch.float32, device=device)

            for step in range(0 if sampling else args.num_steps):
                global_step += args.num_envs
                obs_buf[step] = next_obs
                dones_buf[step] = next_done
                with torch.no_grad():
                    mu, log_std, value = model.heads(next_obs)
                    std = log_std.exp()
                    action = torch.normal(mu, std)  # what Normal(mu, std).sample() does
                    logprobs_buf[step] = normal_log_prob(action, mu, std).sum(-1)
                values_buf[step] = value.squeeze(-1)
                actions_buf[step] = action
                next_obs_np, reward, terminated, truncated, infos = envs.step(action.cpu().numpy())
                done = np.logical_or(terminated, truncated)
                reward = np.asarray(reward, dtype=np.float64).copy()
                # Time-limit truncation is not a real end: bootstrap from the final state.
                idx = np.nonzero(truncated & ~terminated)[0]
                if idx.size and "final_obs" in infos:
                    final = torch.from_numpy(np.stack(infos["final_obs"][idx])).to(device)
                    with torch.no_grad():
                        final_value = model.value(model.preprocess(final))
                    reward[idx] += args.gamma * final_value.cpu().numpy()
                rewards_buf[step] = torch.as_tensor(reward, dtype=torch.float32, device=device)
                for i in np.nonzero(done)[0]:
                    final_info = infos["final_info"]
                    recent_returns.append(float(final_info["episode"]["r"][i]))
                    recent_distances.append(float(final_info["distance"][i]))
                    recent_success.append(float(final_info["is_success"][i]))
                    episodes += 1
                next_obs = model.preprocess(torch.from_numpy(next_obs_np).to(device))
                next_done = torch.as_tensor(done, dtype=torch.float32, device=device)

            # Generalized advantage estimation.
            with torch.no_grad():
                next_value = model.value(next_obs)
            advantages = torch.zeros_like(rewards_buf)
            last_gae = torch.zeros(args.num_envs, device=device)
            for t in reversed(range(args.num_steps)):
                if t == args.num_steps - 1:
                    not_done, following = 1.0 - next_done, next_value
                else:
                    not_done, following = 1.0 - dones_buf[t + 1], values_buf[t + 1]
                delta = rewards_buf[t] + args.gamma * following * not_done - values_buf[t]
                last_gae = delta + args.gamma * args.gae_lambda * not_done * last_gae
                advantages[t] = last_gae
            returns = advantages + values_buf

            torch.set_num_threads(args.update_threads)
            b_obs = obs_buf.reshape((-1, *obs_shape))
            b_actions = actions_buf.reshape(-1, 2)
            b_logprobs = logprobs_buf.reshape(-1)
            b_advantages = advantages.reshape(-1)
            b_returns = returns.reshape(-1)
            clipfracs: list[float] = []
            for _ in range(args.update_epochs):
                order = rng.permutation(batch_size)
                for begin in range(0, batch_size, minibatch_size):
                    mb = torch.from_numpy(order[begin:begin + minibatch_size]).to(device)
                    dist, new_value = model.distribution(b_obs[mb])
                    new_logprob = dist.log_prob(b_actions[mb]).sum(-1)
                    entropy = dist.entropy().sum(-1).mean()
                    log_ratio = new_logprob - b_logprobs[mb]
                    ratio = log_ratio.exp()
                    with torch.no_grad():
                        approx_kl = ((ratio - 1) - log_ratio).mean()
                        clipped = (ratio - 1.0).abs() > args.clip_coef
                        clipfracs.append(clipped.float().mean().item())
                    mb_adv = b_advantages[mb]
                    mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
                    policy_loss = torch.max(
                        -mb_adv * ratio,
                        -mb_adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef),
                    ).mean()
                    value_loss = 0.5 * ((new_value - b_returns[mb]) ** 2).mean()
                    loss = policy_loss - args.ent_coef * entropy + args.vf_coef * value_loss
                    optimizer.zero_grad()
                    loss.backward()
                    torch.nn.utils.clip_grad_norm_(model.parameters(), args.max_grad_norm)
                    optimizer.step()

            torch.set_num_threads(args.torch_threads)
            elapsed = time.perf_counter() - start
            row = {
                "update": update,
                "global_step": global_step,
                "wall_s": round(wall_before + elapsed, 2),
                "steps_per_s": round((global_step - start_step) / max(elapsed, 1e-9), 1),
                "episodes": episodes,
                "mean_return": round(float(np.mean(recent_returns)), 1) if recent_returns else "",
                "mean_final_distance": (
                    round(float(np.mean(recent_distances)), 4) if recent_distances else ""
                ),
                "success_rate": (
                    round(float(np.mean(recent_success)), 3) if recent_success else ""
                ),
                "policy_loss": round(policy_loss.item(), 5),
                "value_loss": round(value_loss.item(), 5),
                "entropy": round(entropy.item(), 4),
                "approx_kl": round(approx_kl.item(), 5),
                "clipfrac": round(float(np.mean(clipfracs)), 4),
                "learning_rate": optimizer.param_groups[0]["lr"],
                "reward_scale": round(float(np.sqrt(normalizer.return_rms.var + 1e-8)), 3),
                "worker_restarts": getattr(envs.unwrapped, "restarts", 0),
            }
            _write_metrics_row(metrics_path, row)
            if writer is not None:
                for key, value in row.items():
                    if key not in ("update", "global_step") and value != "":
                        writer.add_scalar(f"train/{key}", float(value), global_step)
            bar.update(min(global_step, args.total_timesteps) - bar.n)
            bar.set_postfix(sps=row["steps_per_s"], ret=row["mean_return"],
                            succ=row["success_rate"], refresh=False)
            if update % args.checkpoint_every == 0 or global_step >= args.total_timesteps:
                save()
    except KeyboardInterrupt:
        interrupted = True
        save()
    except WorkersLost as exc:
        lost = exc
        if row:  # an update finished in this run: keep what it learned, as Ctrl-C does
            save()
    finally:
        bar.close()
        _close(envs, interrupted)
        if writer is not None:
            writer.close()

    if lost is not None and not row:
        raise lost  # no update finished: nothing learned, an earlier checkpoint stays as it was
    export_model(model.cpu().eval(), out / POLICY_NAME, task=args.task, max_speed=max_speed)
    plot_learning_curve(metrics_path, out / CURVE_NAME)
    summary = {
        "global_step": global_step,
        "updates": num_updates if not row else row["update"],
        "wall_s": wall_before + time.perf_counter() - start,
        "steps_per_s": row.get("steps_per_s"),
        "checkpoint": str(checkpoint_path),
        "policy": str(out / POLICY_NAME),
    }
    if interrupted:
        raise Interrupted(summary)
    if lost is not None:
        lost.summary = summary
        raise lost
    return summary


def _save(path: Path, args: PPOArgs, model: ActorCritic, optimizer: torch.optim.Optimizer,
          reward_rms: Any, global_step: int, update: int, wall_s: float,
          max_speed: float) -> None:
    args_record = {k: v for k, v in asdict(args).items() if k not in ("config", "model")}
    save_checkpoint(path, {
        "task": args.task,
        "model": to_cpu(model.state_dict()),
        "model_config": model.config.to_dict(),
        "optimizer": to_cpu(optimizer.state_dict()),
        "reward_rms": _rms_state(reward_rms),
        "global_step": global_step,
        "update": update,
        "wall_s": wall_s,
        "max_speed": max_speed,
        "args": args_record,
    })


__all__ = ["TASK_DEFAULTS", "Interrupted", "PPOArgs", "plot_learning_curve", "ppo_args", "train",
           "usable_cores"]
