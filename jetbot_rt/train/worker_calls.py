"""Calls to the worker processes of an ``AsyncVectorEnv`` one worker at a time.

Gymnasium's ``call_async`` / ``call_wait`` send a call to every worker and read every answer
at once: a worker that answers first waits for the last before it is given its next call.
PPO's ``--overlap`` gives each worker its next rollout the moment its last one arrives
(``WorkerRollouts``); the rollout's weights are the same for every worker, so this changes
when a worker starts, not what it collects. The messages are gymnasium's own (``("_call",
(name, args, kwargs))`` answered by ``(result, success)``, the error in its error queue).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from multiprocessing.connection import wait
from typing import Any

from gymnasium import logger
from gymnasium.vector import AsyncVectorEnv


class WorkerCalls:
    def __init__(self, vector: AsyncVectorEnv) -> None:
        self.vector = vector
        self.pending: set[int] = set()
        """Workers with a call sent and its answer not yet read."""
        self.last_spread: float | None = None
        """s between the first and the last answer read by the last ``gather``."""

    def send(self, index: int, name: str, args: tuple[Any, ...]) -> None:
        """Call ``name(*args)`` on worker ``index``'s env (its answer read by ``gather``)."""
        if index in self.pending:
            raise RuntimeError(f"worker {index} has a call unanswered")
        self.vector.parent_pipes[index].send(("_call", (name, args, {})))
        self.pending.add(index)

    def send_all(self, name: str, args: tuple[Any, ...]) -> None:
        for index in range(self.vector.num_envs):
            self.send(index, name, args)

    def gather(self, then: Callable[[int], None] | None = None) -> list[Any]:
        """Every pending call's answer, in worker order; ``then(index)`` runs as soon as
        worker ``index`` has answered (before the others are read). The first error read is
        raised as gymnasium raises it, with the other calls left pending."""
        pipes = {self.vector.parent_pipes[index]: index for index in sorted(self.pending)}
        results: list[Any] = [None] * self.vector.num_envs
        first = None
        while pipes:
            for pipe in wait(list(pipes)):
                index = pipes.pop(pipe)  # type: ignore[call-overload]
                result, success = pipe.recv()  # type: ignore[union-attr]
                self.pending.discard(index)
                if not success:
                    self._raise(index)
                results[index] = result
                first = time.perf_counter() if first is None else first
                if then is not None:
                    then(index)
        if first is not None:
            self.last_spread = time.perf_counter() - first
        return results

    def _raise(self, index: int) -> None:
        """Worker ``index``'s error, as gymnasium raises it; every worker's traceback read on
        the way logged. A worker queues its error before it answers, so it is there; other
        workers' errors may be ahead of it."""
        while True:
            worker, error_type, value, trace = self.vector.error_queue.get(timeout=60)
            logger.error(f"Received the following error from Worker-{worker}: {trace}")
            if worker == index:
                raise error_type(value)
