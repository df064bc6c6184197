"""Per-episode memory for tasks whose success is about a whole episode ("never left the
track", "travelled at least this far"), which ``Task.outcome`` (a function of the world as it
is now) cannot see alone.

One record per world: a task instance may serve several envs in one process. A record starts
afresh when the world's ``sim_time`` is back at 0 (the env asks for the outcome right after
each reset) or when the world shows a scene other than the one it was made for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Generic, TypeVar
from weakref import WeakKeyDictionary

from jetbot_rt.tasks.api import WorldView
from jetbot_rt.tasks.scene import Scene

Derived = TypeVar("Derived")


@dataclass
class Episode(Generic[Derived]):
    """What a task remembers about one world's current episode."""

    scene: Scene
    derived: Derived
    """The task's precomputed geometry of ``scene`` and the world (a track, obstacle
    rectangles)."""
    last_xy: tuple[float, float] | None = None
    path_length: float = 0.0
    """m; the axle midpoint's travelled path, summed over steps."""
    failed: bool = False
    """Set once by the task (left the track, touched something): stays set."""
    extra: dict[str, Any] = field(default_factory=dict)

    def advance(self, x: float, y: float) -> float:
        """Add the step's displacement to ``path_length``; returns it (m)."""
        step = 0.0 if self.last_xy is None else math.hypot(x - self.last_xy[0],
                                                            y - self.last_xy[1])
        self.last_xy = (x, y)
        self.path_length += step
        return step


class EpisodeMemory(Generic[Derived]):
    """``episode(scene, world)``: the world's record for this episode, made new as needed;
    ``derive(scene, world)`` computes its ``derived`` once per episode (a module-level
    function: tasks travel to env workers pickled)."""

    def __init__(self, derive: Callable[[Scene, WorldView], Derived]) -> None:
        self._derive = derive
        self._records: WeakKeyDictionary[Any, Episode[Derived]] = WeakKeyDictionary()
        self._fallback: dict[int, Episode[Derived]] = {}

    def episode(self, scene: Scene, world: WorldView) -> Episode[Derived]:
        try:
            record = self._records.get(world)
        except TypeError:  # not weakly referenceable: keyed by id, kept one at a time
            record = self._fallback.get(id(world))
        if record is None or record.scene is not scene or world.sim_time == 0.0:
            # Derived afresh each episode: it may read the world (avoid's clutter), which a
            # reset with the same scene can draw anew.
            record = Episode(scene, self._derive(scene, world))
            try:
                self._records[world] = record
            except TypeError:
                self._fallback.clear()
                self._fallback[id(world)] = record
        return record

    def __getstate__(self) -> dict[str, Any]:  # envs pickle their task to workers
        return {"_derive": self._derive}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["_derive"])  # type: ignore[misc]
