"""One group of a lockstep batch stepped tick by tick (`lockstep.LockstepBackend` makes the groups): its
branches' modules bound to the rows of one stacked bus, each schedule entry stepped once a tick for
every branch (`Module.step_batch`, or the physics' session: `lockstep.PHYSICS`), the inputs written,
the outputs checked and recorded from the rows; a branch that fails leaves the group at once (the
backend runs it again alone). See `lockstep`'s docstring for what makes a branch the same bit for bit.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..kernel.branch import BranchOutcome, BranchStatus
from ..kernel.errors import DynabrainError
from ..kernel.history import WorldState
from ..kernel.module import Module
from ..kernel.structure import SAVE_STATE

if TYPE_CHECKING:
    from .lockstep import _Branch

_EACH = Module.step_batch.__func__  # type: ignore[attr-defined]  # the default: each member alone


@dataclass
class Entry:
    """One module of the schedule, for the whole group: its dispatch entry (of the first branch: the
    copies and timing are the same in each), its N members, whether its class has a batched step,
    and where its inputs and outputs lie on a row."""

    name: str
    period_ns: int
    period_ticks: int
    phase: int
    copies: Any
    gather: Any
    members: list[Module]
    step_batch: Any
    batched: bool
    inputs: slice
    outputs: slice
    ports: str


class LockstepGroup:
    """One group of branches stepped together (see the module docstring)."""

    def __init__(self, branches: list[_Branch], dt_ns: int, bus: np.ndarray, ro: np.ndarray, physics: Any = None,
                 previous: Any = None):
        """``bus``: the group's stacked bus (row k: branch k's, its modules bound to it), ``ro`` the same
        read-only; ``physics``: see `PHYSICS`; ``previous``: the physics' session of the last batch of
        these forks, which it may take again."""
        self.branches, self.dt_ns, self.physics, self.previous = branches, dt_ns, physics, previous
        self.structure = branches[0].start.structure
        self.bus, self.ro = bus, ro
        for row, branch in enumerate(branches):
            bus[row] = branch.start.bus
        self.lengths = np.array([b.task.ticks for b in branches])
        self.session: Any = None
        """The physics' session for this group (`PHYSICS`: ``open``), or None."""
        self.declined = ""
        """Why the physics declined this group ("" if it did not)."""

    def _entries(self) -> list[Entry]:
        layout, out = self.structure.layout, []
        every = [(entry.name, [b.start.structure.records[self._record_index(entry.name)].module
                               for b in self.branches]) for entry in self.structure.dispatch]
        if self.physics is not None and hasattr(self.physics, "open"):
            session = self.physics.open(every, self.previous)
            if isinstance(session, str):
                self.declined = session
            else:
                self.session = session
        for i, (entry, (_name, members)) in enumerate(zip(self.structure.dispatch, every, strict=True)):
            cls = type(members[0])
            slots = layout.modules[entry.name]
            rec = self.structure.records[self._record_index(entry.name)]
            ports = ", ".join(f"{p.name} {p.shape}" for p in rec.outputs if p.view_of is None)
            assert all(b.start.structure.dispatch[i].name == entry.name for b in self.branches)
            step_batch, batched = cls.step_batch, cls.step_batch.__func__ is not _EACH
            if self.session is not None:
                if self.session.handles(entry.name):
                    step_batch, batched = functools.partial(self.session.step_batch, entry.name), True
            elif self.physics is not None and hasattr(self.physics, "handles") and self.physics.handles(cls):
                step_batch, batched = functools.partial(self.physics.step_batch, cls), True
            out.append(Entry(entry.name, entry.period_ns, entry.period_ticks, entry.phase, entry.copies,
                              entry.gather, members, step_batch, batched,
                              slots.inputs_flat or slice(0, 0), slots.outputs_flat or slice(0, 0), ports))
        return out

    def _record_index(self, name: str) -> int:
        index = getattr(self, "_index", None)
        if index is None:
            index = self._index = {rec.name: k for k, rec in enumerate(self.structure.records)}
        return index[name]

    # -- what goes in and what comes out ---------------------------------------------------------------------
    def _slot(self, name: str, settable: bool) -> tuple[int, int, tuple[int, ...]]:
        world = self.branches[0].world
        full = world.settable(name) if settable else name
        slots = self.structure.layout.slots
        slot = slots.get(full) if isinstance(full, str) else None
        if slot is None and world.core is not None:
            slot = slots.get(f"{world.core.name}.{name}")
        if slot is None:
            raise DynabrainError(f"batch backend 'lockstep': no signal {name!r}")
        return slot.start, slot.size, slot.shape

    def _inputs(self, longest: int) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
        """Per input port: (start, stop, the row of its values for each branch or -1, values stacked
        ``(branches that drive it, longest, size)``)."""
        names = list(dict.fromkeys(n for b in self.branches for n in b.task.inputs))
        out = []
        for name in names:
            at, size, _ = self._slot(name, settable=True)
            rows = [r for r, b in enumerate(self.branches) if name in b.task.inputs]
            where = np.full(len(self.branches), -1)
            where[rows] = np.arange(len(rows))
            values = np.zeros((len(rows), longest, size))
            for k, r in enumerate(rows):
                given = np.asarray(self.branches[r].task.inputs[name], dtype=np.float64).reshape(-1, size)
                values[k, :len(given)] = given
            out.append((at, at + size, where, values))
        return out

    def _records(self, longest: int) -> dict[str, tuple[int, int, tuple[int, ...], np.ndarray]]:
        names = list(dict.fromkeys(n for b in self.branches for n in b.task.record))
        out = {}
        for name in names:
            at, size, shape = self._slot(name, settable=False)
            out[name] = (at, at + size, shape, np.full((len(self.branches), longest, size), np.nan))
        return out

    # -- the ticks ---------------------------------------------------------------------------------------------
    def run(self) -> tuple[dict[int, tuple[BranchOutcome, WorldState, int]], list[_Branch]]:
        """Step every branch its ticks; (the outcomes of those that ended well, each with its final state
        and fork, by task index; those that failed)."""
        longest = int(self.lengths.max())
        inputs, records = self._inputs(longest), self._records(longest)
        finals, failed = self._ticks(self._entries(), inputs, records, longest)
        done = {}
        for row, (bus, states) in finals.items():
            done[self.branches[row].task.index] = self._outcome(row, bus, states, records)
        return done, [self.branches[r] for r in sorted(failed)]

    def _ticks(self, entries: list[Entry], inputs: list, records: dict, longest: int) -> tuple[dict, set[int]]:
        bus, structure = self.bus, self.structure
        count = len(self.branches)
        active = np.arange(count)
        failed: set[int] = set()
        finals: dict[int, tuple[np.ndarray, tuple]] = {}
        spans = structure.output_check.spans
        tick0 = self.branches[0].start.tick
        with np.errstate(all="ignore"):  # a failing branch's values are not looked at
            for k in range(longest):
                n = tick0 + k
                t_ns = n * self.dt_ns
                every = len(active) == count
                for a, b, where, values in inputs:
                    if every and where[0] >= 0 and len(values) == count:
                        bus[:, a:b] = values[:, k]
                    else:
                        rows = active[where[active] >= 0]
                        bus[rows, a:b] = values[where[rows], k]
                for dst, src in structure.delayed:
                    bus[:, dst] = bus[:, src]
                for dst, src in structure.delayed_gather:
                    bus[:, dst] = bus[:, src]
                for e in entries:
                    if (n - e.phase) % e.period_ticks:
                        continue
                    for dst, src in e.copies:
                        bus[:, dst] = bus[:, src]
                    for dst, src in e.gather:
                        bus[:, dst] = bus[:, src]
                    bad: dict[int, BaseException] = {}
                    self._step(e, active, every, t_ns, bad)
                    if bad:
                        gone = active[sorted(bad)]
                        failed.update(int(r) for r in gone)
                        active = np.setdiff1d(active, gone)
                        every = False
                rows = slice(None) if len(active) == count else active  # (a slice: no gather)
                if spans and len(active):
                    total = sum(bus[rows, a:b].sum(axis=1) for a, b in spans)
                    finite = np.isfinite(total)
                    if not finite.all():
                        failed.update(int(r) for r in active[~finite])
                        active = active[finite]
                        rows = active
                for a, b, _shape, out in records.values():
                    out[rows, k] = bus[rows, a:b]
                ending = active[self.lengths[active] == k + 1]
                if self.session is not None and len(ending):
                    self.session.sync(ending)
                for row in ending:
                    finals[int(row)] = (bus[row].copy(), self._states(int(row)))
                active = active[self.lengths[active] > k + 1]
                if not len(active):
                    break
        return finals, failed

    def _step(self, e: Entry, active: np.ndarray, every: bool, t_ns: int, bad: dict[int, BaseException]) -> None:
        """Step module ``e`` of the running branches (``active``; ``every``: all of them), once for all
        through its class's batched step, or branch by branch; their failures into ``bad`` (by position
        in ``active``)."""
        members = e.members if every else [e.members[r] for r in active]
        if not e.batched:
            for k, member in enumerate(members):
                try:
                    member.step(t_ns, e.period_ns)
                except Exception as exc:  # this branch fails; it is run again alone
                    bad[k] = exc
            return
        if every:
            inp, out = self.ro[:, e.inputs], self.ro[:, e.outputs]
        else:
            inp, out = self.ro[active, e.inputs], self.ro[active, e.outputs]
        try:
            new = e.step_batch(members, t_ns, e.period_ns, inp, out, bad)
        except Exception as exc:  # for which branch is not known: each is run again alone
            bad.update((k, exc) for k in range(len(members)))
            return
        if new is None:
            return
        if not isinstance(new, np.ndarray) or new.shape != out.shape:
            raise DynabrainError(
                f"module {e.name!r} ({type(members[0]).__name__}): its step_batch returned "
                f"{type(new).__name__ if not isinstance(new, np.ndarray) else f'shape {new.shape}'}; its outputs "
                f"({e.ports}) for {len(members)} branches need an array of shape {out.shape}")
        if every:
            self.bus[:, e.outputs] = new
        else:
            self.bus[active, e.outputs] = new

    # -- the end of a branch --------------------------------------------------------------------------------------
    def _states(self, row: int) -> tuple:
        """Branch ``row``'s modules' states now, as its world's history would save them."""
        start = self.branches[row].start
        return tuple(rec.module.get_state() if kind == SAVE_STATE else saved
                     for rec, kind, saved in zip(start.structure.records, start.structure.saves, start.states,
                                                 strict=True))

    def _outcome(self, row: int, bus: np.ndarray, states: tuple,
                 records: dict) -> tuple[BranchOutcome, WorldState, int]:
        branch = self.branches[row]
        task, start = branch.task, branch.start
        final = WorldState(start.world_id, start.tick + task.ticks, start.structure, bus, states, start.params)
        state = branch.world.export_state(final) if task.keep_state else None
        signals = {name: records[name][3][row, :task.ticks].reshape(task.ticks, *records[name][2])
                   for name in task.record}
        return BranchOutcome(task.index, signals, state, BranchStatus(True, ticks_done=task.ticks)), final, branch.fork
