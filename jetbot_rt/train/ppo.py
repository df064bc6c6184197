"""PPO for the camera-image JetBot tasks (after cleanrl's ``ppo_continuous_action.py``).

``train`` is the loop: collect a rollout (``rollout.py``), compute its advantages (``gae``),
update the network on it (``ppo_update``), log a metrics row, and checkpoint now and then into
the run directory (``run_dir.py``). The reward the learner sees is built by wrappers
(``wrappers.py``): shaping per env, normalisation and clipping over the vector env.

``--critic state`` makes it an asymmetric actor-critic (Pinto et al. 2018): the value is an
MLP of the task's privileged simulator state (``hyperparams.CriticConfig``), read at training
time only; the actor, and so the exported ONNX, is the same image network as ever. Nothing
else changes: the same rollouts, GAE, clipped surrogate and value loss.

``--predict-state W`` (with ``--critic state``) adds a supervised auxiliary loss: a linear
head on the actor's features predicts that privileged state (``ppo_update``).

``--overlap`` collects the next rollout while the learner updates on this one
(``rollout.py``); its samples come from the weights of one update before, each weighed in the
surrogate by ``min(1, pi_learner / pi_collecting)``.
"""

from __future__ import annotations

import contextlib
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from jetbot_rt.tasks import load_task
from jetbot_rt.train.augment import random_shift
from jetbot_rt.train.curriculum import Schedule, curve, metric_fields, send
from jetbot_rt.train.device import resolve_device
from jetbot_rt.train.env import max_speed_of
from jetbot_rt.train.hyperparams import PPOArgs, critic_config
from jetbot_rt.train.model import ActorCritic
from jetbot_rt.train.ray_workers import WorkersLost
from jetbot_rt.train.rollout import BALANCE_CAP, Rollout, RolloutSource, make_rollout_source
from jetbot_rt.train.run_dir import Interrupted, Panel, Progress, RunDirectory, starting_model
from jetbot_rt.train.run_end import close_workers, duplicates_ignored, interrupt_noted

METRIC_FIELDS = (
    "update", "global_step", "wall_s", "steps_per_s", "episodes", "mean_return",
    "mean_final_distance", "success_rate", "policy_loss", "value_loss", "entropy",
    "approx_kl", "clipfrac", "learning_rate", "reward_scale", "worker_restarts",
)
STATE_LOSS = "state_loss"
"""The metrics column of ``--predict-state``'s error (a run without it writes none)."""
EPOCHS = "epochs"
"""The metrics column of the epochs each update ran (``--target-kl``; a run without it writes
none)."""
CURVE = (Panel("mean_return", "mean episode return", scale=("symlog", {"linthresh": 1e4})),
         Panel("success_rate", "training success rate", ylim=(-0.05, 1.05), color="tab:green"))


def gae(rewards: torch.Tensor, values: torch.Tensor, dones: torch.Tensor,
        next_value: torch.Tensor, next_done: torch.Tensor, gamma: float,
        lam: float, lengths: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalized advantage estimation over ``[num_steps, num_envs]`` tensors (``dones[t]``:
    the episode ended before step t); the advantages and the returns (advantage + value).
    ``lengths`` (``--balance``): each env's steps; ``next_value`` and ``next_done`` follow an
    env's last one, and the padding below it gets 0."""
    num_steps = rewards.shape[0]
    advantages = torch.zeros_like(rewards)
    last_gae = torch.zeros(rewards.shape[1], device=rewards.device)
    for t in reversed(range(num_steps)):
        if t == num_steps - 1:
            not_done, following = 1.0 - next_done, next_value
        else:
            not_done, following = 1.0 - dones[t + 1], values[t + 1]
            if lengths is not None:  # an env's last step is followed by its next_value
                last = lengths == t + 1
                not_done = torch.where(last, 1.0 - next_done, not_done)
                following = torch.where(last, next_value, following)
        delta = rewards[t] + gamma * following * not_done - values[t]
        last_gae = delta + gamma * lam * not_done * last_gae
        if lengths is not None:
            last_gae = torch.where(t < lengths, last_gae, torch.zeros_like(last_gae))
        advantages[t] = last_gae
    return advantages, advantages + values


@dataclass(frozen=True)
class UpdateStats:
    """The last minibatch's losses and the share of clipped ratios over the update."""

    policy_loss: float
    value_loss: float
    entropy: float
    approx_kl: float
    clipfrac: float
    epochs: int
    """The epochs run: ``update_epochs``, fewer where ``target_kl`` stopped the update."""
    state_loss: float | None = None
    """The state head's squared error in units of each value's variance over the rollout,
    averaged over the values (``--predict-state``; the mean's error is 1 for a value that
    varies, 0 for one that does not), else None."""


def ppo_update(model: ActorCritic, optimizer: torch.optim.Optimizer, rollout: Rollout,
               advantages: torch.Tensor, returns: torch.Tensor, options: PPOArgs,
               rng: np.random.Generator) -> UpdateStats:
    """``update_epochs`` passes over the rollout in ``num_minibatches`` shuffled minibatches
    (fewer with ``target_kl``: none after the one whose last minibatch passed it):
    the clipped surrogate, the value loss and the entropy bonus, gradients clipped. With the
    asymmetric critic the value is the critic's of ``rollout.states``, and the actor's and
    the critic's gradients are clipped each to their own norm (two networks: the critic's
    gradient does not shrink the actor's step). A rollout collected with older weights
    (``rollout.behaviour_logprobs``) is the decoupled surrogate (Hilton et al. 2021): the
    clip stays around the learner's weights at the update's start (``rollout.logprobs``) and
    each sample is weighed by their probability over the collecting weights', truncated at 1
    as IMPALA's V-trace truncates its ``rho``. With a state head (``--predict-state``) the
    loss adds its weight times the head's squared error on ``rollout.states``, each value
    standardised over the rollout; the head's gradient is clipped on its own, its error's
    share in the encoder's with the actor's."""
    obs = rollout.obs.reshape((-1, *rollout.obs.shape[2:]))
    states = None if rollout.states is None else rollout.states.reshape(
        -1, rollout.states.shape[-1])
    clipped = ([model.actor_parameters(), model.critic_parameters()] if states is not None
               else [list(model.parameters())])
    if model.state_head is not None:
        clipped.append(model.state_head_parameters())
    actions, old_logprobs = rollout.actions.reshape(-1, 2), rollout.logprobs.reshape(-1)
    lag_weights = (None if rollout.behaviour_logprobs is None else
                   (old_logprobs - rollout.behaviour_logprobs.reshape(-1)).exp().clamp(max=1.0))
    advantages, returns = advantages.reshape(-1), returns.reshape(-1)
    valid = rollout.valid
    if valid is not None:  # --balance: the envs' steps, not the padding
        kept = valid.reshape(-1).nonzero().squeeze(1)
        obs, actions, old_logprobs = obs[kept], actions[kept], old_logprobs[kept]
        advantages, returns = advantages[kept], returns[kept]
        states = None if states is None else states[kept]
        lag_weights = None if lag_weights is None else lag_weights[kept]
    batch_size = len(old_logprobs)
    targets = None
    if model.state_head is not None and states is not None:
        # each value in units of its spread over the rollout: the goal's distance and bearing
        # weigh as much as any other, not by their scale (unscaled, their share of the error
        # was a tenth and the head learned nothing from them)
        targets = (states - states.mean(0)) / states.std(0, correction=0).clamp(min=1e-3)
    clip = options.clip_coef
    clipfracs: list[float] = []
    state_loss: torch.Tensor | None = None
    epochs = 0
    for _ in range(options.update_epochs):
        epochs += 1
        # sizes within one of each other, so no minibatch has one sample while another has
        # more (one sample alone, where minibatches outnumber half the batch, is kept as is)
        for part in np.array_split(rng.permutation(batch_size),
                                   min(options.num_minibatches, batch_size)):
            mb = torch.from_numpy(part).to(obs.device)
            dist, new_value, predicted = model.distribution_and_state(
                obs[mb], None if states is None else states[mb])
            new_logprob = dist.log_prob(actions[mb]).sum(-1)
            entropy = dist.entropy().sum(-1).mean()
            log_ratio = new_logprob - old_logprobs[mb]
            ratio = log_ratio.exp()
            with torch.no_grad():
                approx_kl = ((ratio - 1) - log_ratio).mean()
                clipfracs.append(((ratio - 1.0).abs() > clip).float().mean().item())
            mb_adv = advantages[mb]
            if len(part) > 1:  # one sample has no std (NaN): its advantage as it is
                mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
            surrogate = torch.max(-mb_adv * ratio, -mb_adv * ratio.clamp(1 - clip, 1 + clip))
            if lag_weights is not None:
                surrogate = surrogate * lag_weights[mb]
            policy_loss = surrogate.mean()
            value_loss = 0.5 * ((new_value - returns[mb]) ** 2).mean()
            loss = policy_loss - options.ent_coef * entropy + options.vf_coef * value_loss
            if predicted is not None and targets is not None:
                state_loss = ((predicted - targets[mb]) ** 2).mean()
                loss = loss + options.predict_state * state_loss
            if options.augment > 0:
                loss = loss + options.augment * shift_penalty(model, obs[mb], dist, new_value,
                                                              states is None, rng)
            optimizer.zero_grad()
            loss.backward()
            for parameters in clipped:
                torch.nn.utils.clip_grad_norm_(parameters, options.max_grad_norm)
            optimizer.step()
        if options.target_kl is not None and approx_kl.item() > options.target_kl:
            break
    return UpdateStats(policy_loss.item(), value_loss.item(), entropy.item(), approx_kl.item(),
                       float(np.mean(clipfracs)), epochs,
                       None if state_loss is None else state_loss.item())


def shift_penalty(model: ActorCritic, frames: torch.Tensor, dist: torch.distributions.Normal,
                  value: torch.Tensor, image_critic: bool, rng: np.random.Generator
                  ) -> torch.Tensor:
    """DrAC's regulariser: KL(pi(.|frame) || pi(.|shifted frame)) with the first held fixed
    (one std for both: the means' squared distance over twice its variance), plus the image
    critic's squared value change (none with the asymmetric critic: its state is not
    shifted)."""
    mu, _, shifted_value = model.heads(random_shift(frames, rng))
    penalty = ((mu - dist.mean.detach()) ** 2 / (2 * dist.stddev.detach() ** 2)).sum(-1).mean()
    if image_critic:
        penalty = penalty + ((shifted_value.squeeze(-1) - value.detach()) ** 2).mean()
    return penalty


class EpisodeStats:
    """The last ``window`` finished episodes' return, final distance and success."""

    def __init__(self, window: int = 20) -> None:
        self.recent: tuple[deque[float], ...] = tuple(deque(maxlen=window) for _ in range(3))
        self.count = 0

    def add(self, episodes: list[tuple[float, float, float]]) -> None:
        for episode in episodes:
            for values, value in zip(self.recent, episode, strict=True):
                values.append(value)
            self.count += 1

    def row(self) -> dict[str, Any]:
        returns, all_distances, successes = self.recent
        distances = [d for d in all_distances if not np.isnan(d)]  # NaN: the task has none
        return {"episodes": self.count,
                "mean_return": round(float(np.mean(returns)), 1) if returns else "",
                "mean_final_distance": (round(float(np.mean(distances)), 4) if distances
                                        else ""),
                "success_rate": round(float(np.mean(successes)), 3) if successes else ""}


def _tensorboard(path: Any) -> Any:
    """A SummaryWriter into ``path`` when the ``tensorboard`` extra is installed, else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(path))


def _rms_state(rms: Any) -> dict[str, float]:
    return {"mean": float(rms.mean), "var": float(rms.var), "count": float(rms.count)}


def _metrics_row(progress: Progress, episodes: EpisodeStats, stats: UpdateStats,
                 optimizer: torch.optim.Optimizer, source: RolloutSource, options: PPOArgs
                 ) -> dict[str, Any]:
    elapsed = progress.elapsed()
    return {
        "update": progress.update,
        "global_step": progress.global_step,
        "wall_s": round(progress.wall_before + elapsed, 2),
        "steps_per_s": round((progress.global_step - progress.start_step) / max(elapsed, 1e-9),
                             1),
        **episodes.row(),
        "policy_loss": round(stats.policy_loss, 5),
        "value_loss": round(stats.value_loss, 5),
        "entropy": round(stats.entropy, 4),
        "approx_kl": round(stats.approx_kl, 5),
        "clipfrac": round(stats.clipfrac, 4),
        "learning_rate": optimizer.param_groups[0]["lr"],
        "reward_scale": round(float(np.sqrt(source.normalizer.return_rms.var + 1e-8)), 3),
        "worker_restarts": source.restarts,
        **({} if stats.state_loss is None else {STATE_LOSS: round(stats.state_loss, 5)}),
        **({} if options.target_kl is None else {EPOCHS: stats.epochs}),
    }


class _Run:
    """One PPO run's state between its updates: what ``train`` sets up, steps and saves."""

    def __init__(self, options: PPOArgs) -> None:
        options.validate()
        self.options = options
        self.device = resolve_device(options.device)
        fields = (*METRIC_FIELDS, *((STATE_LOSS,) if options.predict_state > 0 else ()),
                  *((EPOCHS,) if options.target_kl is not None else ()))
        self.run = RunDirectory(options.out, metric_fields(fields, options))
        critic = critic_config(options)
        saved = self.run.prepare(options.resume, lambda saved: saved.check_resumable(
            options.task, "ppo", critic))
        torch.manual_seed(options.seed)
        torch.set_num_threads(options.torch_threads)
        model, resumed = starting_model(options, saved, "ppo", critic)
        self.model = model.train().to(self.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=options.learning_rate,
                                          eps=1e-5)
        self.progress = Progress()
        if resumed is not None:
            resumed.load_optimizer(self.optimizer)
            self.progress = Progress(resumed.global_step, resumed.update, resumed.wall_s,
                                     start_step=resumed.global_step)
        self.rng = np.random.default_rng(options.seed + self.progress.update)
        self.max_speed = max_speed_of(options.config, load_task(options.task))
        self.source = make_rollout_source(options, self.model, self.device)
        try:  # train's clean-up starts after this returns: until then, end the workers here
            self.schedule = Schedule.of(options, self.run, resumed is not None,
                                        self.progress.update)
            if self.schedule is not None:
                send(self.source.envs, self.schedule.difficulty)
            if resumed is not None and resumed.reward_rms is not None:
                rms, state = self.source.normalizer.return_rms, resumed.reward_rms
                rms.mean, rms.var, rms.count = (np.float64(state["mean"]),
                                                np.float64(state["var"]), float(state["count"]))
            self.writer = _tensorboard(self.run.inside())
        except BaseException:
            self.source.close(True)
            raise
        self.episodes = EpisodeStats()
        self.steps_per_s: float | None = None

    def update(self) -> dict[str, Any]:
        """Collect a rollout and learn from it; the metrics row."""
        options, model, progress = self.options, self.model, self.progress
        update = progress.update + 1
        if options.anneal_lr:
            frac = max(0.0, 1.0 - progress.global_step / options.total_timesteps)
            self.optimizer.param_groups[0]["lr"] = frac * options.learning_rate
        # With overlap the workers collect the next rollout during this update, unless
        # this may be the last: nothing may be left in flight at the end. A balanced rollout
        # may take up to BALANCE_CAP times its steps (the last one or two then do not overlap).
        longest = options.num_envs * options.num_steps * (BALANCE_CAP if options.balance else 1)
        overlapping = options.overlap and (progress.global_step + longest
                                           < options.total_timesteps)
        rollout = self.source.collect(model, update, prefetch=overlapping)
        self.episodes.add(rollout.episodes)
        with torch.no_grad():
            next_value = model.value(rollout.next_obs, rollout.next_state)
        advantages, returns = gae(rollout.rewards, rollout.values, rollout.dones, next_value,
                                  rollout.next_done, options.gamma, options.gae_lambda,
                                  rollout.lengths)
        # the update's threads take the cores the workers leave idle: none while they collect
        torch.set_num_threads(options.torch_threads if overlapping else options.update_threads)
        stats = ppo_update(model, self.optimizer, rollout, advantages, returns, options,
                           self.rng)
        torch.set_num_threads(options.torch_threads)
        progress.update, progress.global_step = update, progress.global_step + rollout.steps
        row = _metrics_row(progress, self.episodes, stats, self.optimizer, self.source,
                           self.options)
        if self.schedule is not None:
            self.schedule.after(row, (success for *_, success in rollout.episodes),
                                self.source.envs)
        self.steps_per_s = row["steps_per_s"]
        self.run.append_metrics(row)
        if self.writer is not None:
            for key, value in row.items():
                if key not in ("update", "global_step") and value != "":
                    self.writer.add_scalar(f"train/{key}", float(value), progress.global_step)
        return row

    def save(self) -> None:
        self.run.save_checkpoint(algo="ppo", options=self.options, model=self.model,
                                 optimizer=self.optimizer, progress=self.progress,
                                 max_speed=self.max_speed,
                                 reward_rms=_rms_state(self.source.normalizer.return_rms))

    def close(self, interrupted: bool) -> None:
        self.source.close(interrupted)
        if self.writer is not None:
            self.writer.close()

    def finish(self) -> dict[str, Any]:
        """The policy exported, the curve plotted; the summary."""
        self.run.export_policy(self.model.cpu().eval(), self.options.task, self.max_speed,
                               self.options.config)
        self.run.plot_curve("jetbot-train PPO learning curve", curve(CURVE, self.schedule))
        return self.run.summary(self.progress, self.steps_per_s)


def train(options: PPOArgs) -> dict[str, Any]:
    """Run PPO; writes checkpoint, ONNX, metrics and curve to ``options.out``; returns a
    summary. Ctrl-C: writes them as they are and raises ``Interrupted`` (with the summary);
    Ray env workers lost: ``WorkersLost`` (with the summary if an update had finished)."""
    run = _Run(options)
    try:
        return _train(run, options)
    finally:
        run.run.close()


def _train(run: _Run, options: PPOArgs) -> dict[str, Any]:
    with contextlib.ExitStack() as after_interrupt:  # a Ctrl-C's copy: ignored till the export
        return _train_until_done(run, options, after_interrupt)


def _train_until_done(run: _Run, options: PPOArgs, after_interrupt: contextlib.ExitStack
                      ) -> dict[str, Any]:
    progress, total = run.progress, options.total_timesteps
    bar = tqdm(total=total, initial=min(progress.global_step, total),
               disable=not options.progress, unit="step", dynamic_ncols=True)
    first_update = progress.update
    interrupted, lost = False, None
    try:
        run.source.reset(run.model, [options.seed + progress.update * 1000 + i
                                     for i in range(options.num_envs)])
        progress.started = time.perf_counter()  # steps_per_s: the loop's, not the start-up's
        while progress.global_step < total:
            row = run.update()
            bar.update(min(progress.global_step, total) - bar.n)
            bar.set_postfix(sps=row["steps_per_s"], ret=row["mean_return"],
                            succ=row["success_rate"], refresh=False)
            if progress.update % options.checkpoint_every == 0 or progress.global_step >= total:
                run.save()
    except KeyboardInterrupt:
        interrupted = True
        after_interrupt.enter_context(duplicates_ignored())
        run.save()
    except WorkersLost as exc:
        lost = exc
        if progress.update > first_update:  # keep what this run learned, as Ctrl-C does
            run.save()
    finally:
        interrupted = close_workers(run.close, interrupted)
        bar.close()
    if lost is not None and progress.update == first_update:
        raise lost  # nothing learned: an earlier checkpoint stays as it was
    after_interrupt.close()  # from here interrupt_noted notes a copy (and a second raises)
    with interrupt_noted() as noted:
        summary = run.finish()
    if interrupted or noted():
        raise Interrupted(summary)
    if lost is not None:
        lost.summary = summary
        raise lost
    return summary
