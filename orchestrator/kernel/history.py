"""World states and the bounded history ring that `backtick` walks back through.

A history holds up to ``depth + 1`` states, so its memory when full is one state's size times that: a
deep history of a large state (a camera's image is on the bus, so in every state) would exhaust the
machine. The memory a history may hold when full is bounded by a budget (`History.budget`; by default
`default_budget`: half of the machine's memory, or ``DYNABRAIN_HISTORY_BUDGET``). A scenario is refused
at load when its projection is above it (the scenario layer projects it from the modules:
`projected_state_bytes`); a `World` built in Python is refused at its first tick, and at the first tick
after its structure grows (a module or body added), as soon as a state of that structure is known.
"""

from __future__ import annotations

import functools
import os
import re
from collections import deque
from collections.abc import Iterable
from typing import Any

import numpy as np

from .errors import DynabrainError, RollbackError
from .structure import SAVE_STATE, UNRESTORABLE, Structure, _save_kind

BUDGET_ENV = "DYNABRAIN_HISTORY_BUDGET"
"""The environment variable that sets the default budget: bytes (``8GiB``, ``500MB``, ``1000000``) or a
share of the machine's memory (``25%``)."""
BUDGET_SHARE = 0.5
"""The default budget's share of the machine's memory."""
FALLBACK_MEMORY = 8 * 2**30
"""The machine's memory assumed where it cannot be read (8 GiB)."""
STATE_OVERHEAD = 256
"""Bytes of the Python objects of one state besides its arrays (the state, its bus array, its tuples)."""


class HistoryBudgetError(DynabrainError):
    """A history whose memory when full would be above its budget."""


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
        """Approximate memory held by this state (arrays counted by size, `STATE_OVERHEAD` for the rest)."""
        return STATE_OVERHEAD + self.bus.nbytes + sum(_size(s) for s in self.states)

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
    """A bounded ring of world states: the newest is the current tick's; up to ``depth`` behind it.

    ``budget``: the most bytes it may hold when full (None: `default_budget`, read when first needed).
    The first state of each structure (`replace_top`: the world's first state after a change) is
    checked against it (`check`), so a history that would not fit is refused before it grows."""

    def __init__(self, depth: int, budget: int | None = None):
        if depth < 0:
            raise ValueError("history depth must be >= 0")
        self.depth = depth
        self.budget = budget
        self._ring: deque[WorldState] = deque(maxlen=depth + 1)
        self._checked: Structure | None = None  # the structure whose state was last checked

    def __len__(self) -> int:
        return len(self._ring)

    def clear(self) -> None:
        self._ring.clear()

    def push(self, state: WorldState) -> None:
        self._ring.append(state)

    def replace_top(self, state: WorldState) -> None:
        """Make ``state`` the newest (the world's first state after a change); a `HistoryBudgetError`,
        with the ring unchanged, when the states of its structure would fill more than the budget."""
        if state.structure is not self._checked:
            self.check(state.nbytes())
            self._checked = state.structure
        if self._ring and self._ring[-1].tick == state.tick:
            self._ring[-1] = state
        else:
            self._ring.append(state)

    def check(self, state_bytes: int, what: str = "") -> None:
        """Raise a `HistoryBudgetError` when ``depth + 1`` states of ``state_bytes`` each are above the
        budget; ``what`` says what makes a state that large (for the message)."""
        if self.budget is not None:
            budget, source = self.budget, "the world's own: world.history_budget, history.budget"
        else:
            budget, source = default_budget()
        full = state_bytes * (self.depth + 1)
        if full > budget:
            raise HistoryBudgetError(
                f"a history of {self.depth:,} ticks would hold {format_bytes(full)} when full "
                f"({self.depth + 1:,} states of {format_bytes(state_bytes)}{what}), above the history budget of "
                f"{format_bytes(budget)} ({source}); keep fewer ticks (world.history) or raise the budget "
                f"(world.history_budget, {BUDGET_ENV})")

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


def projected_state_bytes(modules: Iterable[Any]) -> dict[str, int]:
    """What each module adds to one state of a world built from ``modules`` (name -> bytes, as
    `WorldState.nbytes` counts them: its ports on the bus and its saved state), and ``""`` ->
    `STATE_OVERHEAD`. Asks each module that saves a state for it (``get_state``) once."""
    out = {"": STATE_OVERHEAD}
    for module in modules:
        ports = [*module.inputs(), *module.outputs()]
        bus = 8 * sum(p.size for p in ports if p.view_of is None)
        out[module.name] = bus + (_size(module.get_state()) if _save_kind(module) == SAVE_STATE else 32)
    return out


# -- the budget ------------------------------------------------------------------------------------------
_UNITS = {"": 1, "b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12,
          "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40}
_SIZE = re.compile(r"\s*([0-9]+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)?)\s*([A-Za-z]*|%)\s*")


def parse_bytes(value: Any, what: str = "a memory size") -> int:
    """A number of bytes from ``value``: a whole number, or a number with a unit (``2GiB``, ``500MB``,
    ``1.5 GB``; B, kB, MB, GB, TB, KiB, MiB, GiB, TiB), or a share of the machine's memory (``25%``).
    A `DynabrainError` names ``what`` when it is none of these, or not above 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise DynabrainError(f"{what} is bytes (2GiB, 500MB) or a share of the machine's memory (25%), got {value!r}")
    if isinstance(value, (int, float)):
        number, unit = float(value), ""
    else:
        match = _SIZE.fullmatch(value)
        if match is None or (match.group(2) != "%" and match.group(2).lower() not in _UNITS):
            raise DynabrainError(f"{what}: {value[:40]!r} is not a size; write bytes with a unit (2GiB, 500MB, "
                                 "B, kB, MB, GB, TB, KiB, MiB, GiB, TiB) or a share of the machine's memory (25%)")
        number, unit = float(match.group(1)), match.group(2)
    if unit == "%":
        if not 0 < number <= 100:
            raise DynabrainError(f"{what}: a share of the machine's memory is above 0% and at most 100%, got {value}")
        return int(machine_memory() * number / 100)
    size = number * _UNITS[unit.lower()]
    if not 1 <= size < 2**63:
        raise DynabrainError(f"{what} must be at least 1 byte (and below 8 EiB), got {value}")
    return int(size)


@functools.cache
def machine_memory() -> int:
    """The memory of this machine in bytes (its physical memory, or a container's limit when lower);
    `FALLBACK_MEMORY` where neither can be read."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        total = 0
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as f:
                text = f.read().strip()
        except OSError:
            continue
        if text.isdigit() and (total <= 0 or 0 < int(text) < total):
            total = int(text)
    return total if total > 0 else FALLBACK_MEMORY


def default_budget() -> tuple[int, str]:
    """(bytes, where they come from) of a history's budget when none is given: ``DYNABRAIN_HISTORY_BUDGET``,
    else `BUDGET_SHARE` of the machine's memory."""
    text = os.environ.get(BUDGET_ENV, "").strip()
    if text:
        return parse_bytes(text, BUDGET_ENV), f"{BUDGET_ENV}={text}"
    total = machine_memory()
    return int(total * BUDGET_SHARE), f"half of this machine's {format_bytes(total)}"


def format_bytes(n: float) -> str:
    """``n`` bytes in the largest binary unit that keeps it at 1 or more (``1.4 TiB``)."""
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"
