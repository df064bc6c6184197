"""PPO's rollouts: where a rollout's actions are computed, behind one interface.

``RolloutSource.collect(model, update)`` steps every env ``num_steps`` times with the policy
of ``model`` and returns a ``Rollout`` (the learner's tensors, on its device). Two sources:

- ``WorkerRollouts``: each env worker process runs a copy of the policy through the whole
  rollout and sends it back at once (``sampler.PolicySampler``); the default with worker
  processes. A round trip to the learner every step serialised the machine (docs/TRAINING.md,
  "Speed").
- ``LearnerRollouts``: the learner computes each step's actions, batched over the envs, on
  its device, and steps the vector env: in its own process (``workers`` 0), in worker
  processes (``sample_in_workers`` off) or on a Ray cluster (``ray``: ``RayVectorEnv``).

Both give the same PPO: the weights are the learner's at the start of the rollout, an episode
that ends is reset in the same step (SAME_STEP), the reward is normalised by the running std
of the discounted return and clipped in step order, and a time-limit truncation is not an end:
its step's reward carries ``gamma`` times the value of the final observation.

With the asymmetric critic (``model.critic``, PPO's ``--critic state``) the envs put the
task's privileged state in their info (``wrappers.CriticState``) and the rollout keeps it
beside each frame (``Rollout.states``): every value -- of a step, of a truncated episode's
final observation, of the next rollout's first -- is the critic's of that state.

With ``overlap`` (PPO's ``--overlap``) ``WorkerRollouts`` sends each worker the next rollout's
call as soon as its part of this one arrives (``worker_calls``), before the learner updates on
this one, so the workers step while the learner learns. That
rollout was collected with the weights of one update before: the learner recomputes its
log-probabilities and values with its own weights (``Rollout.logprobs``, ``values``) and keeps
the collecting weights' (``Rollout.behaviour_logprobs``) for ``ppo.ppo_update``'s importance
weight. A truncated episode's bootstrap value stays the collecting weights' (its final frame
is not sent back).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from gymnasium.vector import VectorEnv

from jetbot_rt.train.device import to_cpu
from jetbot_rt.train.hyperparams import PPOArgs
from jetbot_rt.train.model import ActorCritic, normal_log_prob
from jetbot_rt.train.sampler import PolicySampler, normalize_segment, stack_segments
from jetbot_rt.train.shared_steps import SharedSteps
from jetbot_rt.train.vec_env import EPISODE_INFO, EnvSpec, close_vector_env, make_vector_env
from jetbot_rt.train.worker_calls import WorkerCalls
from jetbot_rt.train.wrappers import CRITIC_STATE, normalize_rewards

BALANCE_CAP = 2
"""``--balance``: a worker takes at most this many times ``num_steps`` in a rollout."""
BALANCE_FLOOR = 4
"""``--balance``: and at least ``num_steps`` over this."""


@dataclass
class Rollout:
    """``num_steps`` steps of ``num_envs`` envs, ``[num_steps, num_envs, ...]`` tensors."""

    obs: torch.Tensor
    """Preprocessed (``ActorCritic.preprocess``): the frame each action was chosen on."""
    actions: torch.Tensor
    logprobs: torch.Tensor
    rewards: torch.Tensor
    """Normalised and clipped, a truncated step's bootstrap added."""
    dones: torch.Tensor
    """Whether the episode ended *before* this step (its observation is a reset's)."""
    values: torch.Tensor
    next_obs: torch.Tensor
    """``[num_envs, ...]``: the next rollout's first observation, preprocessed."""
    next_done: torch.Tensor
    episodes: list[tuple[float, float, float]]
    """(return, final distance, success) of each episode that ended, in step, env order."""
    states: torch.Tensor | None = None
    """With the asymmetric critic: the privileged state of each step's frame
    (``[num_steps, num_envs, state_size]``), which the critic reads; else None."""
    next_state: torch.Tensor | None = None
    """With the asymmetric critic: the state of ``next_obs``."""
    behaviour_logprobs: torch.Tensor | None = None
    """A rollout collected with older weights than the learner's (``overlap``): their
    log-probabilities of its actions, while ``logprobs`` are the learner's; else None."""
    lengths: torch.Tensor | None = None
    """``--balance``: each env's steps (``[num_envs]``); the rows below an env's length are
    padding, in no loss. None: every env has every step."""

    @property
    def steps(self) -> int:
        if self.lengths is not None:
            return int(self.lengths.sum())
        return self.rewards.numel()

    @property
    def valid(self) -> torch.Tensor | None:
        """``[num_steps, num_envs]``: whether the step is an env's (``lengths``); None when
        all are."""
        if self.lengths is None:
            return None
        rows = torch.arange(self.rewards.shape[0], device=self.rewards.device)
        return rows[:, None] < self.lengths[None, :]


class RolloutSource:
    """A vector env, its reward normaliser and the rollout buffers (reused every update)."""

    def __init__(self, envs: VectorEnv, normalizer: Any, options: PPOArgs,
                 device: torch.device, obs_shape: tuple[int, ...], state_size: int = 0) -> None:
        """``state_size``: the asymmetric critic's input width (0: no critic state)."""
        self.envs, self.normalizer, self.options, self.device = envs, normalizer, options, device
        shape = (options.num_steps * (BALANCE_CAP if options.balance else 1), options.num_envs)
        self.obs = torch.zeros((*shape, *obs_shape), device=device)
        self.actions = torch.zeros((*shape, 2), device=device)
        self.logprobs, self.rewards, self.dones, self.values = (
            torch.zeros(shape, device=device) for _ in range(4))
        self.next_obs = torch.zeros((options.num_envs, *obs_shape), device=device)
        self.next_done = torch.zeros(options.num_envs, device=device)
        self.states: torch.Tensor | None = None
        self.next_state: torch.Tensor | None = None
        if state_size:
            self.states = torch.zeros((*shape, state_size), device=device)
            self.next_state = torch.zeros((options.num_envs, state_size), device=device)

    @property
    def restarts(self) -> int:
        """Env workers restarted so far (Ray's); 0 elsewhere."""
        return getattr(self.envs.unwrapped, "restarts", 0)

    def reset(self, model: ActorCritic, seeds: list[int]) -> None:
        frames, infos = self.envs.reset(seed=seeds)
        self.next_obs = model.preprocess(torch.from_numpy(frames).to(self.device))
        self.next_done = torch.zeros(self.options.num_envs, device=self.device)
        if self.states is not None:
            self.next_state = self._states(infos[CRITIC_STATE])

    def _states(self, states: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(states, dtype=np.float32), device=self.device)

    def collect(self, model: ActorCritic, update: int, prefetch: bool = False) -> Rollout:
        """Rollout ``update`` with the policy of ``model``. ``prefetch``: before returning,
        start collecting rollout ``update + 1`` with the same weights (``WorkerRollouts``
        alone; the others ignore it)."""
        raise NotImplementedError

    def close(self, interrupted: bool) -> None:
        close_vector_env(self.envs, interrupted)

    def _rollout(self, episodes: list[tuple[float, float, float]],
                 behaviour_logprobs: torch.Tensor | None = None, rows: int | None = None,
                 lengths: np.ndarray | None = None) -> Rollout:
        """The buffers' first ``rows`` steps (all: None) as a ``Rollout``."""
        part = slice(None) if rows is None else slice(0, rows)
        return Rollout(self.obs[part], self.actions[part], self.logprobs[part],
                       self.rewards[part], self.dones[part], self.values[part], self.next_obs,
                       self.next_done, episodes,
                       None if self.states is None else self.states[part], self.next_state,
                       behaviour_logprobs,
                       None if lengths is None else torch.as_tensor(lengths, device=self.device))


class LearnerRollouts(RolloutSource):
    def collect(self, model: ActorCritic, update: int, prefetch: bool = False) -> Rollout:
        episodes: list[tuple[float, float, float]] = []
        for step in range(self.options.num_steps):
            self.obs[step] = self.next_obs
            self.dones[step] = self.next_done
            if self.states is not None:
                self.states[step] = self.next_state
            with torch.no_grad():
                mu, log_std, value = model.heads(self.next_obs)
                if self.states is not None:
                    value = model.critic_value(self.next_state)[:, None]
                std = log_std.exp()
                action = torch.normal(mu, std)  # what Normal(mu, std).sample() does
                self.logprobs[step] = normal_log_prob(action, mu, std).sum(-1)
            self.values[step] = value.squeeze(-1)
            self.actions[step] = action
            frames, reward, terminated, truncated, infos = self.envs.step(action.cpu().numpy())
            done = np.logical_or(terminated, truncated)
            self.rewards[step] = self._bootstrapped(model, reward, terminated, truncated, infos)
            for i in np.nonzero(done)[0]:
                final_info = infos["final_info"]
                episodes.append((float(final_info["episode"]["r"][i]),
                                 float(final_info["distance"][i]) if "distance" in final_info
                                 else np.nan,  # a task that reports no distance
                                 float(final_info["is_success"][i])))
            self.next_obs = model.preprocess(torch.from_numpy(frames).to(self.device))
            self.next_done = torch.as_tensor(done, dtype=torch.float32, device=self.device)
            if self.states is not None:  # after a reset (SAME_STEP): the reset's state
                self.next_state = self._states(infos[CRITIC_STATE])
        return self._rollout(episodes)

    def _bootstrapped(self, model: ActorCritic, reward: np.ndarray, terminated: np.ndarray,
                      truncated: np.ndarray, infos: dict[str, Any]) -> torch.Tensor:
        """The step's (normalised) reward plus ``gamma`` times the value of the final
        observation where an episode was truncated by the time limit."""
        reward = np.asarray(reward, dtype=np.float64).copy()
        idx = np.nonzero(truncated & ~terminated)[0]
        if idx.size and self.states is not None:
            final_states = self._states(infos["final_info"][CRITIC_STATE][idx])
            with torch.no_grad():
                final_value = model.critic_value(final_states)
            reward[idx] += self.options.gamma * final_value.cpu().numpy()
        elif idx.size and "final_obs" in infos:
            final = torch.from_numpy(np.stack(infos["final_obs"][idx])).to(self.device)
            with torch.no_grad():
                final_value = model.value(model.preprocess(final))
            reward[idx] += self.options.gamma * final_value.cpu().numpy()
        return torch.as_tensor(reward, dtype=torch.float32, device=self.device)


class WorkerRollouts(RolloutSource):
    in_flight: int | None = None
    """The update whose rollout the workers are collecting with older weights (prefetched),
    if any."""
    waiting: bool = False
    """A call to the workers is sent and its answer not yet read."""
    behaviour_logprobs: torch.Tensor | None = None
    calls: WorkerCalls | None = None
    """The workers' pipes, with ``overlap`` (else gymnasium's calls)."""
    shared: SharedSteps | None = None
    """``--balance``: the workers' step counters."""
    pipelined = True
    """With ``overlap``: each worker is sent its next rollout as soon as its last one arrives
    (``worker_calls``) instead of when the last worker's has (one barrier a rollout)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.options.overlap:
            self.calls = WorkerCalls(self.envs.unwrapped)
        if self.options.balance:
            self.shared = SharedSteps.create(self.options.num_envs)

    def _call(self, model: ActorCritic, update: int) -> tuple[Any, ...]:
        """Rollout ``update``'s call; made before any of its sends (it zeroes the rollout's
        step counters with ``--balance``)."""
        # numpy, not tensors: torch pickles a tensor as a shared-memory file descriptor
        # handed over by a resource_sharer thread, which prints a traceback when a worker
        # dies on Ctrl-C mid-handover. Each send pickles them then and there: they must all
        # be sent before the update changes the model's tensors in place.
        weights = {name: w.numpy() for name, w in to_cpu(model.actor_state_dict()).items()}
        options = self.options
        if self.shared is None:
            return weights, options.num_steps, (options.seed, update)
        share = self.shared.share(update, options.num_envs * options.num_steps,
                                  max(1, options.num_steps // BALANCE_FLOOR))
        return weights, BALANCE_CAP * options.num_steps, (options.seed, update), share

    def _send(self, model: ActorCritic, update: int) -> None:
        self.waiting = True
        if self.calls is not None:
            self.calls.send_all("collect", self._call(model, update))
        else:
            self.envs.unwrapped.call_async("collect", *self._call(model, update))

    def _answers(self, model: ActorCritic, update: int, prefetch: bool) -> list[Any]:
        """The workers' segments of rollout ``update``; with ``prefetch`` each worker is
        sent rollout ``update + 1`` (the model's weights now)."""
        if self.calls is None:
            segments = list(self.envs.unwrapped.call_wait())
            self.waiting = False
            if prefetch:
                self._send(model, update + 1)
            return segments
        call = self._call(model, update + 1) if prefetch else None
        then = None
        if call is not None and self.pipelined:
            def then(index: int) -> None:
                self.calls.send(index, "collect", call)  # type: ignore[union-attr]
        segments = self.calls.gather(then)
        if call is not None and not self.pipelined:
            self.calls.send_all("collect", call)
        self.waiting = bool(self.calls.pending)
        return segments

    def collect(self, model: ActorCritic, update: int, prefetch: bool = False) -> Rollout:
        options, device = self.options, self.device
        if self.in_flight is None:
            self._send(model, update)
        elif self.in_flight != update:
            raise RuntimeError(f"rollout {self.in_flight} is in flight, not {update}")
        lagged = self.in_flight is not None
        segment = stack_segments(self._answers(model, update, prefetch))
        self.in_flight = update + 1 if prefetch else None
        rows = len(segment["rewards"])  # num_steps, or the longest segment with --balance
        lengths = None if self.shared is None else segment["lengths"]
        frames = torch.from_numpy(segment["obs"]).to(device)
        obs = self.obs[:rows]
        obs[:] = model.preprocess(frames.flatten(0, 1)).reshape(obs.shape)
        for buf, key in ((self.actions, "actions"), (self.logprobs, "logprobs"),
                         (self.values, "values")):
            buf[:rows] = torch.from_numpy(segment[key]).to(device)
        behaviour = self._learners_view(model, rows) if lagged else None
        done = segment["terminated"] | segment["truncated"]
        self.dones[0] = self.next_done
        self.dones[1:rows] = torch.from_numpy(done[:-1]).to(device)
        reward = normalize_segment(self.normalizer, options.reward_clip, segment["rewards"],
                                   segment["terminated"], segment["truncated"], lengths)
        if self.states is not None:  # the critic's values of the states the workers saw
            self._critic_values(model, segment, rows)
        reward += options.gamma * segment["final_values"]  # 0 where not truncated
        self.rewards[:rows] = torch.as_tensor(reward, dtype=torch.float32, device=device)
        episodes = [(episode_return, distance, success)
                    for _, _, episode_return, distance, success in segment["episodes"]]
        self.next_obs = model.preprocess(torch.from_numpy(segment["next_obs"]).to(device))
        last = done[-1] if lengths is None else done[lengths - 1, np.arange(len(lengths))]
        self.next_done = torch.as_tensor(last, dtype=torch.float32, device=device)
        return self._rollout(episodes, behaviour, rows, lengths)

    def _learners_view(self, model: ActorCritic, rows: int, chunk: int = 1024) -> torch.Tensor:
        """For a rollout (its first ``rows`` steps) collected with older weights:
        ``logprobs`` and ``values`` become the learner's (the image head's values; the
        critic's are set after this); the collecting weights' log-probabilities are
        returned."""
        if self.behaviour_logprobs is None:
            self.behaviour_logprobs = torch.zeros_like(self.logprobs)
        behaviour = self.behaviour_logprobs[:rows]
        behaviour.copy_(self.logprobs[:rows])
        obs, actions = self.obs[:rows].flatten(0, 1), self.actions[:rows].flatten(0, 1)
        logprobs, values = self.logprobs[:rows].view(-1), self.values[:rows].view(-1)
        with torch.no_grad():
            for begin in range(0, len(obs), chunk):
                part = slice(begin, begin + chunk)
                mu, log_std, value = model.heads(obs[part])
                logprobs[part] = normal_log_prob(actions[part], mu, log_std.exp()).sum(-1)
                values[part] = value.squeeze(-1)
        return behaviour

    def close(self, interrupted: bool) -> None:
        # a call still unanswered (an error in the update with a rollout prefetched, a worker
        # lost mid-rollout): gymnasium's close would wait for it, or read a dead pipe again
        # and hide the first error; end the workers instead, as after Ctrl-C
        try:
            close_vector_env(self.envs, interrupted or self.waiting)
        finally:
            if self.shared is not None:
                self.shared.close()
                self.shared = None

    def _critic_values(self, model: ActorCritic, segment: dict[str, Any], rows: int) -> None:
        """Fill ``states``, ``values`` (their first ``rows`` steps) and ``next_state`` from
        the segment's states and set its ``final_values`` to the critic's (the workers ran
        the actor alone)."""
        assert self.states is not None
        states, values = self.states[:rows], self.values[:rows]
        states[:] = self._states(segment["states"])
        self.next_state = self._states(segment["next_state"])
        bootstrapped = segment["truncated"] & ~segment["terminated"]
        with torch.no_grad():
            values[:] = model.critic_value(states.flatten(0, 1)).reshape(values.shape)
            final = model.critic_value(self._states(segment["final_states"]).flatten(0, 1))
        segment["final_values"] = np.where(bootstrapped, final.cpu().numpy().reshape(
            bootstrapped.shape), 0.0)


def make_rollout_source(options: PPOArgs, model: ActorCritic,
                        device: torch.device) -> RolloutSource:
    """The source ``options`` ask for, with its vector env started."""
    sampling = options.samples_in_workers
    critic = model.critic_config
    spec = EnvSpec(options.task, options.config, options.shaping, model.config.image_size,
                   keep=EPISODE_INFO if critic is None else (*EPISODE_INFO, CRITIC_STATE),
                   sampler=PolicySampler if sampling else None,
                   model=model.config if sampling else None, critic_state=critic is not None)
    envs, normalizer = normalize_rewards(
        make_vector_env(spec, options.num_envs, options.workers, ray=options.ray,
                        ray_max_restarts=options.ray_max_restarts),
        options.gamma, options.reward_clip)
    with torch.no_grad():
        frame = torch.zeros((1, *envs.single_observation_space.shape))
        obs_shape = tuple(model.preprocess(frame).shape[1:])
    source = WorkerRollouts if sampling else LearnerRollouts
    return source(envs, normalizer, options, device, obs_shape,
                  0 if critic is None else critic.state_size)
