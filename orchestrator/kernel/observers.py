"""Observers: a logger, a bridge publisher or a viewer sees the world after each tick, read-only.

They are told about rollbacks and restores, so a log never presents a discarded future as the run,
about edits (modules added or removed, parameters set, make, joints) as events, and about what the
brain imagined (`World.imagine`: a predicted or planned branch it asks to keep, as `Imagined`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from .world import World


@dataclass(frozen=True)
class WorldEvent:
    """Something that happened to the world at a tick: ``kind`` and a plain ``detail`` dict.

    ``source`` is ``"scenario"`` for an edit made by one of the scenario's scheduled events (a replay
    of the scenario makes it again by itself) and ``"api"`` for anything else (a brain's call, a
    bridge client): a replay must apply those from the log.
    """

    tick: int
    kind: str
    detail: dict[str, Any] = field(default_factory=dict)
    source: str = "api"
    edit: Any = field(default=None, compare=False)
    """The edit as a typed record (`kernel.edits`) when the event is one; ``detail`` is its `Edit.detail`."""


@dataclass(frozen=True)
class Imagined:
    """A future the brain imagined and asks to keep (`World.imagine`): branch ``branch`` of ``name``
    (a plan, a batch of predictions), starting from the world's state at ``start_tick``. Row k of each
    signal is its value after tick ``start_tick + k + 1`` (at ``(start_tick + k + 1) * dt_ns`` ns of
    simulated time), shape ``(ticks, *signal shape)``; the arrays are read-only copies. ``units`` gives
    each signal's unit ("" for a signal the world does not have). ``tick`` is the world's tick when it
    was imagined."""

    name: str
    branch: int
    start_tick: int
    dt_ns: int
    signals: Mapping[str, np.ndarray] = field(repr=False)
    units: Mapping[str, str] = field(repr=False)
    tick: int = 0

    @property
    def ticks(self) -> int:
        """How many ticks it spans."""
        return len(next(iter(self.signals.values())))


class WorldView:
    """A read-only view of a world, handed to observers."""

    def __init__(self, world: World):
        self._world = world

    @property
    def name(self) -> str:
        return self._world.name

    @property
    def tick(self) -> int:
        return self._world.tick_count

    @property
    def time(self) -> float:
        return self._world.time

    @property
    def dt_ns(self) -> int:
        return self._world.dt_ns

    def get(self, name: str) -> Any:
        return self._world.get(name)

    def signals(self) -> list[str]:
        return self._world.signals

    def bus(self) -> np.ndarray:
        """The whole bus as a read-only array (layout from `signal_slots`); the same array object
        until the world's structure changes."""
        return self._world.bus

    def signal_slots(self) -> dict[str, tuple[int, tuple[int, ...], str]]:
        """signal -> (offset in `bus`, shape, unit)."""
        return {n: (s.start, s.shape, s.port.unit) for n, s in self._world.structure.layout.slots.items()}

    @property
    def core(self):
        return self._world.core


class Observer:
    """Base class with no-op hooks; override what you need. Hooks run on the stepping thread,
    under the world lock: keep them short, and do not call the world's editing API from them."""

    def on_tick(self, view: WorldView) -> None:
        """After each tick."""

    def on_rollback(self, view: WorldView, from_tick: int) -> None:
        """The world went back from ``from_tick`` to ``view.tick`` (backtick, restore, failed tick)."""

    def on_event(self, view: WorldView, event: WorldEvent) -> None:
        """An edit or a notable event."""

    def on_imagined(self, view: WorldView, imagined: Imagined) -> None:
        """The brain imagined a future and asks to keep it (`World.imagine`). It is not the run: a
        rollback does not discard it."""

    def on_close(self, view: WorldView) -> None:
        """The world is closing."""
