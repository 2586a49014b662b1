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
from collections.abc import Callable, Iterable
from itertools import islice
from typing import Any, NamedTuple

import numpy as np

from .errors import DynabrainError, RollbackError
from .portable import UNRESTORABLE
from .structure import SAVE_STATE, Structure, save_kind

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

    def entry(self) -> tuple:
        """The state as history holds it: ``(world_id, tick, structure, bus, params, id, *states)``, the
        bus an array or its bytes (`from_entry` makes the state again)."""
        return (self.world_id, self.tick, self.structure, self.bus, self.params, self.id, *self.states)

    @staticmethod
    def from_entry(entry: tuple) -> WorldState:
        """The state history holds as ``entry`` (`entry`'s form); a bus kept as bytes comes back as a
        read-only array on them."""
        world_id, tick, structure, bus, params, id = entry[:6]
        if type(bus) is bytes:
            bus = np.frombuffer(bus)
        return WorldState(world_id, tick, structure, bus, entry[6:], params, id)

    def nbytes(self) -> int:
        """Approximate memory held by this state (arrays counted by size, `STATE_OVERHEAD` for the rest)."""
        return STATE_OVERHEAD + self.bus.nbytes + sum(_size(s) for s in self.states)

    def unrestorable(self) -> list[str]:
        return [rec.name for rec, st in zip(self.structure.records, self.states, strict=True) if st is UNRESTORABLE]


class Written:
    """A tick between keyframes whose inputs were written before its step (`History.written`): the bus
    spans written, ``(start, values as bytes)``, in the order they were written. Stepping again from the
    keyframe before it writes them again at this tick (`History.restore_point`)."""

    __slots__ = ("spans", "tick")

    def __init__(self, tick: int, spans: list[tuple[int, bytes]]):
        self.tick = tick
        self.spans = spans

    def __repr__(self) -> str:
        return f"<Written tick={self.tick} spans={len(self.spans)}>"


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


class RestorePoint(NamedTuple):
    """Where a rollback to a tick starts (`History.restore_point`)."""

    state: WorldState
    """The newest keyframe at or before that tick."""
    ahead: int
    """How many ticks after the keyframe that tick is (stepped again from it)."""
    inputs: list[list[tuple[int, bytes]] | None]
    """For each of those ticks, the inputs written at it (``(bus offset, bytes)``), or None."""


class History:
    """A bounded ring of world states: the newest is the current tick's; up to ``depth`` behind it.

    The ring holds each state as a plain tuple (`WorldState.entry`), which the world's capture makes in
    its generated code (`compiled.state_saver`, with the bus as bytes: cheaper to make and to drop than
    an array) and hands to `appender`'s append: a `WorldState` object is made only when one is read
    (`top`, `peek_back`).

    ``budget``: the most bytes it may hold when full (None: `default_budget`, read when first needed).
    The first state of each structure (`replace_top`: the world's first state after a change) is
    checked against it (`check`), so a history that would not fit is refused before it grows.

    ``every``: keyframes. 1 (History's default; a `World` keeps one every 2 ticks unless told
    otherwise): a state every tick. k > 1: a state every k ticks (at ticks
    that are multiples of k), and after every edit or event (the world pushes those whole); the ticks
    between hold only their number, or (`Written`) the inputs written at them before their step, and
    `restore_point` gives the keyframe before a tick, how many ticks the world steps again from it to
    reach that tick (`World.backtick`) and the inputs to write again on the way. It trades the cost of
    a state each tick for up to k - 1 ticks stepped again at each backtick (see docs/concepts.md,
    "History with keyframes")."""

    def __init__(self, depth: int, budget: int | None = None, every: int = 1):
        if depth < 0:
            raise ValueError("history depth must be >= 0")
        if not isinstance(every, int) or isinstance(every, bool) or every < 1:
            raise ValueError(f"keyframes every {every!r} ticks: a whole number >= 1")
        self.depth = depth
        self.budget = budget
        self.every = every
        # a keyframe at or before the oldest tick within ``depth`` is always kept
        self._ring: deque[tuple | int | Written] = deque(maxlen=depth + every)
        self._checked: Structure | None = None  # the structure whose state was last checked

    def __len__(self) -> int:
        return len(self._ring)

    def clear(self) -> None:
        self._ring.clear()

    def push(self, state: WorldState) -> None:
        self._ring.append(state.entry())

    def appender(self) -> Callable[[tuple], None]:
        """The call that pushes an entry (`WorldState.entry`'s form): the world's capture after a tick."""
        return self._ring.append

    def replace_top(self, state: WorldState) -> None:
        """Make ``state`` the newest (the world's first state after a change); a `HistoryBudgetError`,
        with the ring unchanged, when the states of its structure would fill more than the budget."""
        if state.structure is not self._checked:
            self.check(state.nbytes())
            self._checked = state.structure
        if self._ring and _tick_of(self._ring[-1]) == state.tick:
            self._ring[-1] = state.entry()
        else:
            self._ring.append(state.entry())

    def written(self, tick: int, spans: list[tuple[int, bytes]], bus: Callable[[], bytes]) -> bool:
        """Keep inputs written into the bus at ``tick`` before its step (``spans``: ``(start, values as
        bytes)``; they change only the bus, so this spares the world a capture of every module): the
        newest entry, when it is ``tick``'s, takes them: a state takes the whole bus (``bus()``), a tick
        between keyframes the spans (`Written`: stepping again from its keyframe writes them again).
        False when the newest entry is another tick's (the world then captures the state instead)."""
        ring = self._ring
        if not ring:
            return False
        top = ring[-1]
        kind = type(top)
        if kind is tuple:
            if top[1] != tick:
                return False
            ring[-1] = (*top[:3], bus(), *top[4:])
        elif kind is Written:
            if top.tick != tick:
                return False
            top.spans += spans
        else:
            if top != tick:
                return False
            ring[-1] = Written(tick, spans)
        return True

    def check(self, state_bytes: int, what: str = "") -> None:
        """Raise a `HistoryBudgetError` when `states_when_full` states of ``state_bytes`` each are above
        the budget; ``what`` says what makes a state that large (for the message)."""
        if self.budget is not None:
            budget, source = self.budget, "the world's own: world.history_budget, history.budget"
        else:
            budget, source = default_budget()
        full = state_bytes * self.states_when_full
        if full > budget:
            raise HistoryBudgetError(
                f"a history of {self.depth:,} ticks would hold {format_bytes(full)} when full "
                f"({self.states_when_full:,} states of {format_bytes(state_bytes)}{what}), above the history budget of "
                f"{format_bytes(budget)} ({source}); keep fewer ticks (world.history) or raise the budget "
                f"(world.history_budget, {BUDGET_ENV})")

    @property
    def states_when_full(self) -> int:
        """How many states the ring holds at most (edits and events aside, which add keyframes)."""
        return self.depth + 1 if self.every == 1 else self.depth // self.every + 2

    @property
    def top(self) -> WorldState:
        """The newest state (a `RollbackError` when its tick holds no state: keyframes, `restore_point`)."""
        return self.peek_back(0)

    @property
    def available(self) -> int:
        """How many ticks back `backtick` can go."""
        if self.every == 1:
            return max(len(self._ring) - 1, 0)
        for oldest, entry in enumerate(self._ring):  # the oldest keyframe: at most `every` entries in
            if type(entry) is tuple:
                return min(len(self._ring) - 1 - oldest, self.depth)
        return 0

    def peek_back(self, n: int) -> WorldState:
        """The state ``n`` ticks back (a `RollbackError` when that tick holds no state: keyframes,
        `restore_point`)."""
        self._check_back(n)
        entry = self._ring[-1 - n]
        if type(entry) is not tuple:
            raise RollbackError(f"tick {entry} holds no state (keyframes every {self.every} ticks): "
                                "its keyframe and the ticks to step from it are restore_point's")
        return WorldState.from_entry(entry)

    def restore_point(self, n: int) -> RestorePoint:
        """(the newest keyframe at or before ``n`` ticks back, how many ticks after it that tick is, and for
        each of those ticks the inputs written at it: `Written` spans, or None): the state itself, 0 and
        no inputs where that tick holds one (always, with a state every tick)."""
        self._check_back(n)
        ring, at = self._ring, len(self._ring) - 1 - n
        for ahead in range(at + 1):
            entry = ring[at - ahead]
            if type(entry) is tuple:
                inputs = [e.spans if type(e) is Written else None for e in islice(ring, at - ahead + 1, at + 1)]
                return RestorePoint(WorldState.from_entry(entry), ahead, inputs)
        raise RollbackError(f"backtick({n}): no keyframe kept before it")  # `available` keeps one

    def _check_back(self, n: int) -> None:
        if n < 0:
            raise RollbackError(f"backtick({n}): n must be >= 0")
        if n > self.available:
            raise RollbackError(f"backtick({n}) goes beyond the history: only {self.available} ticks are kept "
                                f"(history depth {self.depth}: raise it with World(history=...) in Python, "
                                "world: {history: ...} in a scenario)")

    def drop_newest(self, n: int) -> None:
        for _ in range(n):
            self._ring.pop()

    def memory_bytes(self) -> int:
        """Memory held by the ring now, estimated from its newest state."""
        return self._newest_bytes() * self._states()

    def describe(self) -> str:
        per, states = self._newest_bytes(), self._states()
        # keyframes asked for, but a whole state at every tick: a module that cannot roll back (or an edit each tick)
        whole = self.every > 1 and len(self._ring) > self.every and states == len(self._ring)
        most = (self._ring.maxlen or 0) if whole else self.states_when_full
        how = (" (a whole state every tick: a module cannot roll back, or every tick was edited)" if whole
               else f" (keyframes every {self.every} ticks)" if self.every > 1 else "")
        return f"{states} of {most} states{how}, ~{per / 1024:.1f} KiB each, ~{per * most / 2**20:.1f} MiB when full"

    def _states(self) -> int:
        return len(self._ring) if self.every == 1 else sum(type(e) is tuple for e in self._ring)

    def _newest_bytes(self) -> int:
        newest = next((e for e in reversed(self._ring) if type(e) is tuple), None)
        return WorldState.from_entry(newest).nbytes() if newest is not None else 0


def _tick_of(entry: tuple | int | Written) -> int:
    """The tick of an entry of the ring: a state's (`WorldState.entry`), or a tick's between keyframes
    (its number, or `Written`)."""
    kind = type(entry)
    return entry[1] if kind is tuple else entry.tick if kind is Written else entry


def projected_state_bytes(modules: Iterable[Any]) -> dict[str, int]:
    """What each module adds to one state of a world built from ``modules`` (name -> bytes, as
    `WorldState.nbytes` counts them: its ports on the bus and its saved state), and ``""`` ->
    `STATE_OVERHEAD`. Asks each module that saves a state for it (``get_state``) once."""
    out = {"": STATE_OVERHEAD}
    for module in modules:
        ports = [*module.inputs(), *module.outputs()]
        bus = 8 * sum(p.size for p in ports if p.view_of is None)
        out[module.name] = bus + (_size(module.get_state()) if save_kind(module) == SAVE_STATE else 32)
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
