"""The vector env the trainers step: PPO's and DAgger's envs, built the same way.

Each env is the task's env with the trainer's reward (``wrappers.make_train_env``), keeping
only the info keys the trainer reads (``KeepInfo``) and, where the workers run the policy, a
sampler around it (``sampler.PolicySampler`` for PPO, ``dagger_sampler.LabelSampler`` for
DAgger). They run one per worker process (``AsyncVectorEnv``, started with ``spawn``), all in
the learner's process (``SyncVectorEnv``, ``workers`` 0), or as actors of a Ray cluster
(``ray_workers.RayVectorEnv``). Gymnasium 1.x vector envs autoreset in the *next* step by
default, which would put a reset observation paired with an ignored action into a rollout:
every one here resets in the SAME_STEP.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial
from typing import Any

import gymnasium as gym
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv, VectorEnv

from jetbot_rt.config.sections import Config
from jetbot_rt.train.hyperparams import ModelConfig
from jetbot_rt.train.wrappers import KeepInfo, Shaping, make_train_env


@contextlib.contextmanager
def workers_ignore_the_working_directory() -> Iterator[None]:
    """Around the start of ``spawn`` workers. A spawned worker is ``python -c``, which puts the
    working directory first on ``sys.path`` before it imports anything: a ``threading.py`` or
    ``jetbot_rt/`` planted where someone trains would run as them. ``PYTHONSAFEPATH`` (Python
    3.11+) leaves it out; it is set only while the workers start, so this process's other
    children (a script run by name needs its own directory on ``sys.path``) are as before.
    Python 3.10 has no such switch (docs/SAFETY.md)."""
    previous = os.environ.get("PYTHONSAFEPATH")
    os.environ["PYTHONSAFEPATH"] = "1"
    try:
        yield
    finally:
        if previous is None:
            del os.environ["PYTHONSAFEPATH"]
        else:
            os.environ["PYTHONSAFEPATH"] = previous


EPISODE_INFO = ("episode", "distance", "is_success")
"""The only ``info`` keys PPO reads (at an episode's end); the workers drop the rest."""


@dataclass(frozen=True)
class EnvSpec:
    """What each env of a vector env is (picklable: a worker process builds its env from
    it)."""

    task: str
    config: Config
    shaping: Shaping
    image_size: int
    keep: tuple[str, ...] = EPISODE_INFO
    """The info keys the trainer reads."""
    sampler: type | None = None
    """A wrapper class ``(env, model, index)`` that runs the policy in the worker."""
    model: ModelConfig | None = None
    """The network the sampler runs."""
    critic_state: bool = False
    """Put the task's privileged state in each info (``wrappers.CriticState``; keep
    ``"critic_state"`` too): PPO's asymmetric critic reads it."""


def worker_env(spec: EnvSpec, index: int) -> gym.Env:
    """Env ``index`` of a vector env, built inside its worker. Ctrl-C is the learner's to
    handle (it saves a checkpoint, then ends the workers), not a traceback from every worker."""
    if multiprocessing.parent_process() is not None:  # AsyncVectorEnv also calls it here
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    size = (spec.image_size, spec.image_size)
    env = KeepInfo(make_train_env(spec.task, spec.config, spec.shaping, image_size=size,
                                  critic_state=spec.critic_state), spec.keep)
    return env if spec.sampler is None else spec.sampler(env, spec.model, index)


def make_vector_env(spec: EnvSpec, num_envs: int, workers: int | None, *,
                    ray: str | None = None, ray_max_restarts: int = 3) -> VectorEnv:
    """``num_envs`` envs of ``spec``: on Ray when ``ray`` is an address (``workers`` actors),
    else in this process (``workers`` 0) or one worker process each."""
    factories = [partial(worker_env, spec, i) for i in range(num_envs)]
    if ray is not None:
        from jetbot_rt.train.ray_workers import RayVectorEnv  # imports ray

        return RayVectorEnv(factories, address=ray, workers=workers,
                            max_restarts=ray_max_restarts)
    if workers == 0:
        return SyncVectorEnv(factories, autoreset_mode=AutoresetMode.SAME_STEP)
    with workers_ignore_the_working_directory():
        return AsyncVectorEnv(factories, context="spawn",
                              autoreset_mode=AutoresetMode.SAME_STEP, shared_memory=True)


def close_vector_env(envs: Any, interrupted: bool) -> None:
    """Close the env workers. Ctrl-C can stop the learner half-way through reading a worker's
    message (a whole rollout or DAgger iteration is one call to the workers, so it mostly
    waits in that read): the rest in the pipe cannot be read, and gymnasium's close would read
    it (EOFError, exit 1 instead of 130) or wait for the call to finish. After Ctrl-C the
    worker processes are ended and nothing more is read."""
    vector = envs.unwrapped
    if not (interrupted and isinstance(vector, AsyncVectorEnv)):
        envs.close()
        return
    for process in vector.processes:
        process.terminate()
    for process in vector.processes:
        process.join()
    for pipe in vector.parent_pipes:
        if pipe is not None:  # gymnasium drops a failed worker's
            pipe.close()
    vector.closed = True  # its __del__ would try again
