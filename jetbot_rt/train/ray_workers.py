"""Env workers on a Ray cluster, behind the vector-env interface PPO already consumes.

``RayVectorEnv`` is a Gymnasium ``VectorEnv`` (SAME_STEP autoreset, like the trainer's
``AsyncVectorEnv``): ``num_envs`` envs split over ``workers`` Ray actors, worker ``w`` hosting a
contiguous block of env indices. Each step the driver sends every actor its block of actions
and gathers the results in worker-index order, so a seeded run does not depend on which actor
answers first. The learner (and the policy's forward pass, batched over all envs, on CUDA when
there is one) stays in the driver; what crosses the wire per step is the actions (8 bytes an
env) one way and the frame at the policy's size (56x56x3 uint8: 9.4 KiB an env) plus rewards
and infos the other.
Replies under Ray's inline limit (100 KiB) ride on the RPC itself; larger ones go through the
object store, shared memory on one node. docs/TRAINING.md says why per step and not whole
rollouts per update.

Faults: an actor whose process or node dies mid-step is restarted by Ray (``max_restarts``
per actor), its envs are rebuilt and reset with fresh seeds derived from the run's seeds and
the restart count (a run with the same faults replays the same), and the step in flight gets
their reset observations (reward 0, not done: one transition of the rollout spans the
restart). The driver waits at most ``restart_timeout`` s for the actor to come back, then
raises ``WorkersLost``. ``restarts`` counts the events; each is also one line on stderr.

``ray`` is imported only here, and this module only when the trainer is asked for Ray.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array

from jetbot_rt.errors import first_line
from jetbot_rt.train.hyperparams import OptionError

PROBE_TIMEOUT_S = 5.0
"""How long ``connect`` waits for a TCP answer from a cluster address (Ray itself retries an
unreachable head for minutes)."""
RESEED_STRIDE = 7919
"""A restarted env's new seed: its first seed + RESEED_STRIDE * the worker's restart count."""


class WorkersLost(RuntimeError):
    """An env worker died and did not come back within the restart bound. ``summary``: the
    trainer's summary when it saved a checkpoint before giving up, else None."""

    summary: dict[str, Any] | None = None


def _import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise OptionError("ray", "needs Ray: pip install 'jetbot_rt[cluster]' (on every node "
                                 "of the cluster)") from None
    return ray


class EnvWorker:
    """A Ray actor hosting several envs of the task (SAME_STEP autoreset, as SyncVectorEnv)."""

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]]) -> None:
        # Ctrl-C belongs to the driver: it saves a checkpoint, then ends the workers.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        self.envs = [fn() for fn in env_fns]

    def spaces(self) -> tuple[gym.Space, gym.Space]:
        return self.envs[0].observation_space, self.envs[0].action_space

    def reset(self, seeds: Sequence[int | None], options: dict[str, Any] | None
              ) -> tuple[np.ndarray, list[dict[str, Any]]]:
        results = [env.reset(seed=seed, options=options)
                   for env, seed in zip(self.envs, seeds, strict=True)]
        return np.stack([obs for obs, _ in results]), [info for _, info in results]

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                 np.ndarray, list[dict[str, Any]]]:
        frames, rewards, terminated, truncated, infos = [], [], [], [], []
        for env, action in zip(self.envs, actions, strict=True):
            obs, reward, term, trunc, info = env.step(action)
            if term or trunc:
                final = {"final_obs": obs, "final_info": info}
                obs, info = env.reset()
                info = {**final, **info}
            frames.append(obs)
            rewards.append(reward)
            terminated.append(term)
            truncated.append(trunc)
            infos.append(info)
        return (np.stack(frames), np.asarray(rewards, dtype=np.float64),
                np.asarray(terminated, dtype=np.bool_), np.asarray(truncated, dtype=np.bool_),
                infos)

    def set_attr(self, name: str, values: Sequence[Any]) -> None:
        for env, value in zip(self.envs, values, strict=True):
            env.set_wrapper_attr(name, value)

    def close(self) -> None:
        for env in self.envs:
            env.close()


def split(num_envs: int, workers: int) -> list[range]:
    """Contiguous env-index blocks, sizes differing by at most one, in worker order."""
    base, extra = divmod(num_envs, workers)
    blocks, start = [], 0
    for w in range(workers):
        size = base + (1 if w < extra else 0)
        blocks.append(range(start, start + size))
        start += size
    return blocks


def _probe(address: str) -> None:
    """``OptionError`` unless something accepts a TCP connection at ``[ray://]HOST:PORT``."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise OptionError("ray", f"{address}: expected local, auto, HOST:PORT or "
                                 f"ray://HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), PROBE_TIMEOUT_S).close()
    except OSError as exc:
        raise OptionError("ray", f"{address}: no Ray head answers there "
                                 f"({exc.strerror or exc}); start one with `ray start --head` "
                                 "(docs/TRAINING.md)") from None


def connect(address: str) -> bool:
    """``ray.init`` for the ``ray`` option's address: ``local`` starts Ray on this machine, anything
    else (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``) joins that cluster. Returns whether
    this call started the connection (then ``RayVectorEnv.close`` ends it)."""
    ray = _import_ray()
    if ray.is_initialized():
        return False
    kwargs: dict[str, Any] = {"address": address, "log_to_driver": False}
    if address == "local":  # a new Ray of our own, even if this machine has a cluster running
        kwargs["include_dashboard"] = False
    elif address != "auto":
        _probe(address)
    try:
        ray.init(**kwargs)
    except (ConnectionError, ValueError) as exc:  # no cluster; ray:// without ray[client]
        raise OptionError("ray", f"{address}: {first_line(exc)}") from None
    return True


class RayVectorEnv(VectorEnv):
    """``num_envs`` = ``len(env_fns)`` envs on ``workers`` Ray actors (module docstring)."""

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], *, address: str = "local",
                 workers: int | None = None, max_restarts: int = 3,
                 restart_timeout: float = 120.0, step_timeout: float = 300.0) -> None:
        ray = _import_ray()
        self._ray = ray
        self._owns_ray = connect(address)
        self.num_envs = len(env_fns)
        cpus = int(ray.cluster_resources().get("CPU", 0))
        workers = workers or max(1, min(self.num_envs, cpus))
        if workers > self.num_envs:
            raise OptionError("workers", f"{workers} is more than num_envs {self.num_envs}")
        if workers > cpus:
            raise OptionError("workers", f"{workers} need one CPU each; the Ray cluster has "
                                         f"{cpus}")
        self.blocks = split(self.num_envs, workers)
        self.max_restarts = max_restarts
        self.restart_timeout = restart_timeout
        self.step_timeout = step_timeout
        self.restarts = 0
        self.worker_restarts = [0] * workers
        self._seeds: list[int | None] = [None] * self.num_envs
        self._attrs: dict[str, list[Any]] = {}
        """What ``set_attr`` set, by name: set again on an actor Ray restarts."""
        remote = ray.remote(num_cpus=1, max_restarts=max_restarts, max_task_retries=0,
                            scheduling_strategy="SPREAD")(EnvWorker)
        self.actors = [remote.remote([env_fns[i] for i in block]) for block in self.blocks]
        try:  # every actor built its envs (a node without the sim, a different version...)
            single_obs, single_act = ray.get([a.spaces.remote() for a in self.actors])[0]
        except ray.exceptions.RayActorError as exc:
            self.close_extras()
            lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
            raise OptionError("ray", f"cluster: an env worker could not start "
                                     f"({lines[-1][:200]}); every node needs "
                                     "jetbot_rt[sim,train,cluster] of this version") from None
        self.single_observation_space = single_obs
        self.single_action_space = single_act
        self.observation_space = batch_space(single_obs, self.num_envs)
        self.action_space = batch_space(single_act, self.num_envs)
        self.metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}
        self.render_mode = None
        self._obs = create_empty_array(single_obs, self.num_envs)

    # -- the VectorEnv interface ---------------------------------------------------------
    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(f"{len(seeds)} seeds for {self.num_envs} envs")
        self._seeds = seeds
        refs = [actor.reset.remote([seeds[i] for i in block], options)
                for actor, block in zip(self.actors, self.blocks, strict=True)]
        results = [self._get(w, ref) for w, ref in enumerate(refs)]
        infos: dict[str, Any] = {}
        frames = []
        for w, result in enumerate(results):
            if result is None:
                result = self._recover(w)
            frames.append(result[0])
            for i, info in zip(self.blocks[w], result[1], strict=True):
                infos = self._add_info(infos, info, i)
        self._obs = concatenate(self.single_observation_space, np.concatenate(frames),
                                self._obs)
        return self._obs.copy(), infos

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                 np.ndarray, dict[str, Any]]:
        actions = np.asarray(actions)
        refs = [actor.step.remote(actions[block.start:block.stop])
                for actor, block in zip(self.actors, self.blocks, strict=True)]
        frames, rewards, terminated, truncated = [], [], [], []
        infos: dict[str, Any] = {}
        for w, ref in enumerate(refs):
            result = self._get(w, ref)
            if result is None:
                obs, reset_infos = self._recover(w)
                n = len(self.blocks[w])
                result = (obs, np.zeros(n), np.zeros(n, np.bool_), np.zeros(n, np.bool_),
                          [{**info, "worker_restarted": True} for info in reset_infos])
            frames.append(result[0])
            rewards.append(result[1])
            terminated.append(result[2])
            truncated.append(result[3])
            for i, info in zip(self.blocks[w], result[4], strict=True):
                infos = self._add_info(infos, info, i)
        self._obs = np.concatenate(frames)
        return (self._obs.copy(), np.concatenate(rewards), np.concatenate(terminated),
                np.concatenate(truncated), infos)

    def set_attr(self, name: str, values: Any) -> None:
        """Set an attribute of every env (``values``: one per env, or one for all), as
        ``AsyncVectorEnv.set_attr`` does (the curriculum's difficulty)."""
        values = list(values) if isinstance(values, (list, tuple)) else [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(f"{len(values)} values for {self.num_envs} envs")
        self._attrs[name] = values
        lost = (self._ray.exceptions.RayActorError, self._ray.exceptions.ActorUnavailableError,
                self._ray.exceptions.GetTimeoutError)
        for actor, block in zip(self.actors, self.blocks, strict=True):
            with contextlib.suppress(*lost):  # the next step finds it gone; _recover sets
                self._ray.get(self._set_attrs(actor, block, {name: values}),  # them again
                              timeout=self.step_timeout)

    @staticmethod
    def _set_attrs(actor: Any, block: range, attrs: dict[str, list[Any]]) -> list[Any]:
        return [actor.set_attr.remote(name, values[block.start:block.stop])
                for name, values in attrs.items()]

    def close_extras(self, **kwargs: Any) -> None:
        ray = self._ray
        for actor in self.actors:
            ray.kill(actor, no_restart=True)
        self.actors = []
        if self._owns_ray:
            ray.shutdown()

    # -- faults --------------------------------------------------------------------------
    def _get(self, worker: int, ref: Any) -> Any:
        """The actor's reply, or None if it died (or went silent for step_timeout s)."""
        ray = self._ray
        try:
            return ray.get(ref, timeout=self.step_timeout)
        except ray.exceptions.GetTimeoutError:
            ray.kill(self.actors[worker], no_restart=False)  # silent: make Ray restart it
            return None
        except (ray.exceptions.RayActorError, ray.exceptions.ActorUnavailableError):
            return None

    def _recover(self, worker: int) -> tuple[np.ndarray, list[dict[str, Any]]]:
        """Wait for Ray to restart the worker, then reset its envs with fresh seeds."""
        ray = self._ray
        self.restarts += 1
        self.worker_restarts[worker] += 1
        count = self.worker_restarts[worker]
        block = self.blocks[worker]
        if count <= self.max_restarts:
            print(f"jetbot-train: Ray env worker {worker} (envs {block.start}.."
                  f"{block.stop - 1}) lost; restart {count} of at most {self.max_restarts}",
                  file=sys.stderr)
        seeds = [None if self._seeds[i] is None else self._seeds[i] + RESEED_STRIDE * count
                 for i in block]
        deadline = time.monotonic() + self.restart_timeout
        while True:
            remaining = deadline - time.monotonic()
            try:
                self._set_attrs(self.actors[worker], block, self._attrs)  # before the reset
                return ray.get(self.actors[worker].reset.remote(seeds, None),
                               timeout=max(remaining, 0.001))
            except ray.exceptions.ActorDiedError:
                if count > self.max_restarts:
                    raise WorkersLost(f"Ray env worker {worker} died and was not restarted "
                                      f"({self.max_restarts} restarts at most)") from None
            except (ray.exceptions.RayActorError, ray.exceptions.ActorUnavailableError,
                    ray.exceptions.GetTimeoutError):
                pass
            if time.monotonic() >= deadline:
                raise WorkersLost(f"Ray env worker {worker} did not come back within "
                                  f"{self.restart_timeout:g} s")
            time.sleep(0.2)


__all__ = ["RayVectorEnv", "WorkersLost", "connect", "split"]
