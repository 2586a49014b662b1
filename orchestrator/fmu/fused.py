"""FMUs stepped as one: a chain of FMU modules next to each other in the schedule costs one call from
Python per tick instead of one per FMU.

`FMUModule.fuse` answers the compiled tick's question (`Module.fuse`) with a `FusedFMUs` when every
member steps on the C helper's path (reals on the bus, states kept for history, no events). Its
tick call makes one ctypes call to ``dyn_group`` (``csrc/dyn_step.c``): for each member in schedule
order, the bus copies of its inputs, then ``dyn_step`` (SetReal, DoStep, GetReal, the finite check,
GetFMUstate), exactly the calls the separate steps make, so the results are the same bit for bit.

The members' states of one tick are one `GroupState`: one row of handles (one per member) in a
`GroupPool`, taken and given back as one, instead of an `FMUState` object per member. Each member's
`get_state` returns that same object; `set_state` restores the member's own handle from it. Pickled
(an exported state, a state sent to another process) it becomes a `GroupSerialized`, each member's
serialized state by module name.

Measured with ``bench/fmu_chain.py`` (10 pass-through FMUs, history on, this 2-core machine): 0.84 us
per FMU-step with a call per member, about 0.3 with the chain fused. A member that stops qualifying
(a failure it cannot restore, an event, another step size) makes the chain step member by member,
in Python, until the structure is built again.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .fastpath import ENDED, group_helper
from .states import SerializedFMUState

if TYPE_CHECKING:
    from ..kernel.structure import Copies
    from .module import FMUModule


class _Copy(ctypes.Structure):
    _fields_ = [("dst", ctypes.c_size_t), ("src", ctypes.c_size_t), ("n", ctypes.c_size_t)]


class _Group(ctypes.Structure):
    """Mirror of ``Group`` in dyn_step.c."""

    _fields_ = [("n", ctypes.c_size_t), ("plans", ctypes.c_void_p), ("first_copy", ctypes.c_void_p),
                ("copies", ctypes.c_void_p), ("bus", ctypes.c_void_p), ("codes", ctypes.c_void_p)]


@dataclass(frozen=True)
class GroupSerialized:
    """The states of fused FMU modules as bytes, each member's by its module name."""

    names: tuple[str, ...]
    states: tuple[SerializedFMUState, ...]

    def of(self, name: str) -> SerializedFMUState:
        try:
            return self.states[self.names.index(name)]
        except ValueError:
            raise KeyError(f"this state holds the FMU states of {', '.join(self.names)}, not of {name!r}") from None


class GroupPool:
    """Rows of state handles, one column per member; a row is one tick's states of the whole group."""

    def __init__(self, members: Sequence[FMUModule], capacity: int = 16):
        self.members = tuple(members)
        self.column = {id(m): i for i, m in enumerate(members)}
        self.slots = np.zeros((capacity, len(members)), dtype=np.uint64)
        self.base = self.slots.ctypes.data
        self.stride = 8 * len(members)
        self.free = list(range(capacity - 1, -1, -1))

    def take(self) -> int:
        if self.free:
            return self.free.pop()
        n = len(self.slots)
        bigger = np.zeros((2 * n, self.slots.shape[1]), dtype=np.uint64)
        bigger[:n] = self.slots
        self.slots, self.base = bigger, bigger.ctypes.data
        self.free.extend(range(2 * n - 1, n, -1))
        return n

    def handle(self, row: int, member: FMUModule) -> int:
        return int(self.slots[row, self.column[id(member)]])


    def close_member(self, member: FMUModule) -> None:
        """Free the member's handles (its instance is about to go); its column is of no use after."""
        i = self.column.pop(id(member), None)
        session = member._session
        api = session.api if session is not None else None
        if i is None or api is None or api.instance is None or api.dead:
            return
        for row in np.flatnonzero(self.slots[:, i]):
            try:
                api.free_state(self.base + int(row) * self.stride + 8 * i)
            except Exception:  # the FMU's leak, not a reason to stop
                continue
        self.slots[:, i] = 0


class GroupState:
    """The states of every member of a `FusedFMUs` after one tick (a row of a `GroupPool`). Immutable;
    dropping it gives the row back."""

    __slots__ = ("pool", "row")

    def __init__(self, pool: GroupPool, row: int):
        self.pool = pool
        self.row = row

    def __del__(self) -> None:
        self.pool.free.append(self.row)

    def handle(self, member: FMUModule) -> int | None:
        """The member's FMU state handle, or None (not a member, or its instance is gone)."""
        pool = self.pool
        return pool.handle(self.row, member) if id(member) in pool.column else None

    def serialized(self, name: str) -> SerializedFMUState:
        """The state of the member called ``name`` as bytes (for another instance of its FMU: a fork)."""
        for m in self.pool.members:
            handle = self.handle(m)
            if m.name == name and handle is not None:
                return m._session.serialize_handle(handle)
        raise KeyError(f"{self!r} holds no live state of a module {name!r}")

    def __reduce__(self) -> tuple:
        names = tuple(m.name for m in self.pool.members if id(m) in self.pool.column)
        return (GroupSerialized, (names, tuple(self.serialized(n) for n in names)))

    def __repr__(self) -> str:
        return f"<GroupState of {', '.join(m.name for m in self.pool.members)}>"


class FusedFMUs:
    """FMU modules stepped as one (`Module.fuse`'s answer for `FMUModule`). Whether the members
    qualify is checked at the first tick after each bind and after a member says it changed
    (``ok`` set to None); while they do not, the members step one by one."""

    def __init__(self, members: Sequence[FMUModule], copies: Sequence[Copies], fn: Callable[..., int]):
        self.members = tuple(members)
        self.failing: str | None = None
        self.pool = GroupPool(members)
        for m in members:
            m._group_pools.add(self.pool)
        self._fn = fn
        runs: list[tuple[int, int, int]] = []
        first = [0]
        for pairs in copies:
            runs.extend(_run(dst, src) for dst, src in pairs)
            first.append(len(runs))
        self._copies = (_Copy * max(len(runs), 1))(*(_Copy(*r) for r in runs))
        self._first = np.array(first, dtype=np.uintp)
        self._plans = np.zeros(len(members), dtype=np.uintp)
        self._codes = np.zeros(len(members), dtype=np.intc)
        self._py_copies = tuple(copies)
        self.ok: bool | None = None
        self.keeps = False
        self.dt_ns = 0

    @classmethod
    def make(cls, members: Sequence[FMUModule], copies: Sequence[Copies]) -> FusedFMUs | None:
        fn = group_helper()
        return None if fn is None else cls(members, copies, fn)

    def _check(self) -> bool:
        """Whether every member steps on the C path now (and with one step size); takes their plans."""
        members = self.members
        ok = (all(m._fusable() for m in members) and len({m._dt_ns for m in members}) == 1
              and len({m._pool is None for m in members}) == 1)
        self.keeps = ok and members[0]._pool is not None  # states for history, or none
        if ok:
            self._plans[:] = [ctypes.addressof(m._session.stepper.plan) for m in members]
            self.dt_ns = members[0]._dt_ns
            for m in members:
                m._fused = self
        self.ok = ok
        return ok

    def bind(self, buf: np.ndarray) -> Callable[[int, int], None]:
        group = _Group(len(self.members), self._plans.ctypes.data, self._first.ctypes.data,
                       ctypes.addressof(self._copies), buf.ctypes.data, self._codes.ctypes.data)
        arg = ctypes.addressof(group)
        fn, pool, members = self._fn, self.pool, self.members
        mv = memoryview(buf)
        pairs = tuple(zip(self._py_copies, (m.step for m in members), members, strict=True))
        free, take = pool.free, pool.take
        self.ok = None  # the members bind after the tick: look at them at the first call

        def step(t_ns: int, period_ns: int, keep: Any = (group, buf)) -> None:
            ok = self.ok
            if ok is None:
                ok = self._check()
            if not ok or period_ns != self.dt_ns:
                return self._one_by_one(t_ns, period_ns, mv, pairs)
            if not self.keeps:
                rc = fn(arg, t_ns, 0)
                if rc:
                    self._failed(rc, -1, t_ns)
                return None
            row = free.pop() if free else take()
            rc = fn(arg, t_ns, pool.base + pool.stride * row)
            if rc:
                self._failed(rc, row, t_ns)
            state = GroupState(pool, row)
            for m in members:
                m._state = state
            return None

        return step

    def _one_by_one(self, t_ns: int, dt_ns: int, mv: memoryview, pairs: tuple) -> None:
        for copies, step, member in pairs:
            self.failing = member.name
            for dst, src in copies:
                mv[dst] = mv[src]
            step(t_ns, dt_ns)
        self.failing = None

    def _failed(self, rc: int, row: int, t_ns: int) -> None:
        """Warnings are logged member by member; the first member that failed raises (and the row goes
        back: the world rolls the tick back)."""
        codes = self._codes
        if rc > 0 and row >= 0:
            self.pool.free.append(row)
        for i, m in enumerate(self.members):
            code = int(codes[i])
            if code & 15 in (1, ENDED):  # a warning; a step that stands and asks to end (the member says so)
                m._failed(code, -1, t_ns)
            elif code:
                self.failing = m.name
                m._failed(code, -1, t_ns)  # raises


def step_each(members: Sequence[FMUModule], t_ns: int, failed: dict[int, BaseException]) -> bool:
    """Step ``members`` (instances on the hot path, each bound to its own row of a lockstep batch's bus)
    in one call to ``dyn_group`` from ``t_ns``, saving no state; a member whose step fails goes into
    ``failed`` (its index -> the error its own step raises) and those after it go on in a call of their
    own. False (nothing stepped) without the C helper. The servo FMU's world (`scenarios/fmu_servo.yaml`),
    64 branches x 500 ticks in lockstep: 180k ticks/s against 161k with a Python call per instance."""
    fn = group_helper()
    if fn is None:
        return False
    n = len(members)
    plans = np.array([ctypes.addressof(m._session.stepper.plan) for m in members], dtype=np.uintp)
    first = np.zeros(n + 1, dtype=np.uintp)  # no bus copies between members (the lockstep made them), so the
    codes = np.zeros(n, dtype=np.intc)  # group's copy list and bus are never read: any valid address will do
    none = (_Copy * 1)()
    start = 0
    while start < n:
        group = _Group(n - start, plans.ctypes.data + plans.itemsize * start, first.ctypes.data,
                       ctypes.addressof(none), plans.ctypes.data, codes.ctypes.data + codes.itemsize * start)
        rc = fn(ctypes.addressof(group), t_ns, 0)
        stop = start + rc if rc > 0 else n  # (rc > 0: member start + rc - 1 failed, those after it did not step)
        for i in range(start, stop):
            code = int(codes[i])
            if code:
                try:
                    members[i]._failed(code, -1, t_ns)  # a warning is logged; a failure raises
                except Exception as exc:  # this branch's failure
                    failed[i] = exc
        start = stop
    return True


def _run(dst: Any, src: Any) -> tuple[int, int, int]:
    """(dst start, src start, count) of a bus copy made of single indices or plain slices."""
    if isinstance(dst, slice):
        return int(dst.start or 0), int(src.start or 0), int(dst.stop - (dst.start or 0))
    return int(dst), int(src), 1
