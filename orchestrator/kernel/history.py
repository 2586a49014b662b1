"""World states and the bounded history ring that `backtick` walks back through."""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from .errors import RollbackError
from .structure import UNRESTORABLE, Structure


class WorldState:
    """Everything that changes while a world runs, at one tick.

    ``states[i]`` is the state of ``structure.records[i]``'s module (`UNRESTORABLE` for a module that
    cannot roll back) and ``params[i]`` its parameter values. The parameter dicts are copy-on-write,
    and consecutive states share one tuple of them until a parameter changes, so keeping them costs
    a reference. ``world_id`` ties a snapshot to the world (and module objects) it came from.
    """

    __slots__ = ("bus", "id", "params", "states", "structure", "tick", "world_id")

    def __init__(self, world_id: int, tick: int, structure: Structure, bus: np.ndarray, states: tuple[Any, ...],
                 params: tuple[dict[str, Any], ...], id: int = 0):
        # a plain class with slots: one is made every tick, and a frozen dataclass costs ~1 us more
        self.world_id = world_id
        self.tick = tick
        self.structure = structure
        self.bus = bus
        self.states = states
        self.params = params
        self.id = id
        """A snapshot's number within its world (1, 2, ...); 0 for history entries."""

    def __repr__(self) -> str:
        return f"<WorldState tick={self.tick} modules={len(self.states)} bus={self.bus.size}>"

    def nbytes(self) -> int:
        """Approximate memory held by this state (arrays counted by size)."""
        return self.bus.nbytes + sum(_size(s) for s in self.states)

    def unrestorable(self) -> list[str]:
        return [rec.name for rec, st in zip(self.structure.records, self.states, strict=True) if st is UNRESTORABLE]


def _size(value: Any) -> int:
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, (tuple, list)):
        return 56 + sum(_size(v) for v in value)
    if isinstance(value, dict):
        return 232 + sum(_size(v) for v in value.values())
    if isinstance(value, (bytes, bytearray)):
        return len(value)
    return 32


class History:
    """A bounded ring of world states: the newest is the current tick's; up to ``depth`` behind it."""

    def __init__(self, depth: int):
        if depth < 0:
            raise ValueError("history depth must be >= 0")
        self.depth = depth
        self._ring: deque[WorldState] = deque(maxlen=depth + 1)

    def __len__(self) -> int:
        return len(self._ring)

    def clear(self) -> None:
        self._ring.clear()

    def push(self, state: WorldState) -> None:
        self._ring.append(state)

    def replace_top(self, state: WorldState) -> None:
        if self._ring and self._ring[-1].tick == state.tick:
            self._ring[-1] = state
        else:
            self._ring.append(state)

    @property
    def top(self) -> WorldState:
        return self._ring[-1]

    @property
    def available(self) -> int:
        """How many ticks back `backtick` can go."""
        return max(len(self._ring) - 1, 0)

    def peek_back(self, n: int) -> WorldState:
        if n < 0:
            raise RollbackError(f"backtick({n}): n must be >= 0")
        if n > self.available:
            raise RollbackError(f"backtick({n}) goes beyond the history: only {self.available} ticks are kept "
                                f"(history depth {self.depth}; raise `world.history` in the scenario)")
        return self._ring[-1 - n]

    def drop_newest(self, n: int) -> None:
        for _ in range(n):
            self._ring.pop()

    def memory_bytes(self) -> int:
        """Memory held by the ring now, estimated from its newest entry."""
        return self._ring[-1].nbytes() * len(self._ring) if self._ring else 0

    def describe(self) -> str:
        per = self._ring[-1].nbytes() if self._ring else 0
        return (f"{len(self._ring)} of {self.depth + 1} states, ~{per / 1024:.1f} KiB each, "
                f"~{per * (self.depth + 1) / 2**20:.1f} MiB when full")
