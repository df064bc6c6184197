"""The env steps each worker has taken in the current rollout, in shared memory, for PPO's
``--balance``: every worker keeps stepping until the workers together have the rollout's
steps, so none waits for the one in the dearest scene.

Two banks, used by alternate rollouts: with ``--overlap`` a worker may start rollout u + 1
while others still step rollout u. The learner zeroes rollout u's bank before it sends any
of its calls; by then every worker has answered rollout u - 2, the bank's last user. Each
worker writes only its own slot (an aligned 8-byte store), and reads the others' to sum them.
"""

from __future__ import annotations

from dataclasses import dataclass
from multiprocessing import shared_memory

import numpy as np

BANKS = 2


@dataclass(frozen=True)
class Share:
    """A worker's part in a balanced rollout: the counters' ``name`` and number of
    ``workers``, the rollout's ``bank``, the ``total`` env steps the workers take together
    and the ``min_steps`` each takes."""

    name: str
    workers: int
    bank: int
    total: int
    min_steps: int


class SharedSteps:
    """``counts[bank, worker]``: env steps taken in the bank's rollout."""

    def __init__(self, memory: shared_memory.SharedMemory, num_envs: int, owner: bool) -> None:
        self.memory, self.owner = memory, owner
        self.counts = np.ndarray((BANKS, num_envs), dtype=np.int64, buffer=memory.buf)
        self.workers = num_envs

    @classmethod
    def create(cls, num_envs: int) -> SharedSteps:
        """The learner's: zeroed; ``close`` removes it."""
        memory = shared_memory.SharedMemory(create=True, size=8 * BANKS * num_envs)
        steps = cls(memory, num_envs, owner=True)
        steps.counts[:] = 0
        return steps

    @classmethod
    def attach(cls, name: str, num_envs: int) -> SharedSteps:
        """A worker's view of the learner's counters. (The attach registers the name with the
        resource tracker the learner shares with its spawned workers, a set: the learner's
        unlink unregisters it once for both.)"""
        return cls(shared_memory.SharedMemory(name=name), num_envs, owner=False)

    @property
    def name(self) -> str:
        return self.memory.name

    def share(self, update: int, total: int, min_steps: int) -> Share:
        """Rollout ``update``'s ``Share``, its bank zeroed: call before any of its sends."""
        bank = update % BANKS
        self.counts[bank] = 0
        return Share(self.name, self.workers, bank, total, min_steps)

    def close(self) -> None:
        """Unmaps the counters (and removes them, the learner's): an array still viewing
        them would then read unmapped memory, so none outlives its call (``collect``'s view
        is a local)."""
        del self.counts
        self.memory.close()
        if self.owner:
            self.memory.unlink()
