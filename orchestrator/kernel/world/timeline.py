"""The timeline: a world's states in history, snapshots, rollback (backtick, restore, a failed tick
undone) and fork, the copy of a world in the same state (as a Context clone is to Drake).

History keeps a whole state at keyframes and the tick's number between them (`History`); going back
to a tick between keyframes applies the keyframe before it and steps the ticks after it again
(`replay`), writing the inputs that were written then.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..compiled import state_saver
from ..errors import ForkError, RollbackError
from ..history import WorldState
from ..module import Module
from ..portable import UNRESTORABLE
from ..structure import SAVE_NONE, SAVE_PARAMS, Structure, rebind_structure
from .context import Context
from .util import close_quietly


class Timeline:
    """History, snapshots, rollback and fork of one world (see the module docstring)."""

    def __init__(self, ctx: Context):
        self.ctx = ctx
        self._snapshots = itertools.count(1)

    # -- states ---------------------------------------------------------------------------------------
    def capture(self) -> WorldState:
        ctx = self.ctx
        structure = ctx.structure
        if ctx.saver_of is not structure:
            self.make_saver(structure)
        return WorldState(ctx.id, ctx.tick, structure, ctx.buf.copy(), ctx.save_states(), ctx.params)

    def make_saver(self, structure: Structure) -> None:
        """What each state of history holds until the structure or a parameter changes, or a state is
        restored: the modules' parameter dicts (one shared tuple), the state of each module whose
        steps leave it alone (`Module.steps_change_state`: saved now, then shared), and a call to
        ``get_state`` for the others; and ``ctx.record``, which pushes such a state after a tick."""
        ctx = self.ctx
        ctx.params = tuple([rec.module.param_state() for rec in structure.records])
        entries: list[tuple[bool, Any]] = []
        for rec, how in zip(structure.records, structure.saves, strict=True):
            module = rec.module
            if how == SAVE_NONE:
                entries.append((False, UNRESTORABLE))
            elif how == SAVE_PARAMS:
                entries.append((False, None))
            elif module.steps_change_state():
                entries.append((True, module.get_state))
            else:
                entries.append((False, module.get_state()))
        # the bus goes into history as bytes (`History`): half the cost of an array's copy, to make and to drop;
        # a state every tick while a module cannot roll back (stepping it again would repeat what it did)
        every = 1 if SAVE_NONE in structure.saves else ctx.history.every
        ctx.save_states, ctx.record = state_saver(entries, ctx.history.appender(), ctx.mv.tobytes,
                                                  (ctx.id, structure, ctx.params), every)
        ctx.saver_of = structure

    def apply(self, state: WorldState) -> None:
        ctx = self.ctx
        if state.structure is not ctx.structure:
            ctx.install(state.structure, carry_values=False)
        np.copyto(ctx.buf, state.bus)
        for rec, saved, params in zip(state.structure.records, state.states, state.params, strict=True):
            if saved is not UNRESTORABLE:
                rec.module.restore_param_state(params)
                rec.module.set_state(saved)
        ctx.tick = state.tick
        ctx.saver_of = None  # the states kept as they were may have been restored to others

    def check_restorable(self, state: WorldState, what: str) -> None:
        bad = state.unrestorable()
        if bad:
            raise RollbackError(f"{what} refused: module(s) {', '.join(bad)} cannot roll back "
                                "(capability can_rollback is false)")

    def keep_inputs(self, spans: list[tuple[int, bytes]]) -> None:
        """Inputs just written into the bus at this tick (``(start, values as bytes)``), for history's
        state of this tick (`History.written`); when history cannot take them, the next tick saves a
        whole state."""
        ctx = self.ctx
        if not ctx.dirty and not ctx.history.written(ctx.tick, spans, ctx.mv.tobytes):
            ctx.dirty = True

    # -- going back -----------------------------------------------------------------------------------
    def backtick(self, n: int) -> None:
        ctx = self.ctx
        point = ctx.history.restore_point(n)
        self.check_restorable(point.state, f"backtick({n})")
        from_tick = ctx.tick
        ctx.history.drop_newest(n)
        self.apply(point.state)
        self.replay(point.ahead, point.inputs)
        ctx.dirty = False
        ctx.rolled_back(from_tick)

    def back_to(self, n: int) -> None:
        """Make the world what it was ``n`` ticks ago (0: at the current tick, after a failed one), from
        history's keyframe and the ticks stepped again after it; history itself is left as it is."""
        point = self.ctx.history.restore_point(n)
        self.apply(point.state)
        self.replay(point.ahead, point.inputs)

    def replay(self, ticks: int, inputs: Sequence[Sequence[tuple[int, bytes]] | None]) -> None:
        """Step ``ticks`` ticks again from the keyframe just applied, as they ran: no events (a keyframe
        follows every tick that had some), no history entries, no observers; ``inputs[k]``: the inputs
        written before the step after the k-th (`History.restore_point`), written again. Steps that do
        not repeat themselves (a module that is not deterministic) raise a `RollbackError`, the world
        left at the keyframe and history cut after it."""
        ctx = self.ctx
        dt_ns, mv = ctx.dt_ns, ctx.mv.cast("B")
        for done in range(ticks):
            n = ctx.tick
            try:
                ctx.run_tick(n, n * dt_ns)
            except Exception as exc:
                keyframe = n - done
                ctx.history.drop_newest(ticks)  # the ticks after the keyframe
                self.apply(ctx.history.top)
                raise RollbackError(f"stepping again from the keyframe at tick {keyframe} to tick {keyframe + ticks} "
                                    f"failed at tick {n} ({exc}); the world is at tick {keyframe}") from exc
            ctx.tick = n + 1
            for start, data in inputs[done] or ():
                mv[8 * start:8 * start + len(data)] = data

    # -- snapshots ------------------------------------------------------------------------------------
    def snapshot(self) -> WorldState:
        state = self.capture()
        state.id = next(self._snapshots)
        self.ctx.emit("snapshot", id=state.id)
        return state

    def restore(self, state: WorldState, **event: Any) -> None:
        """Make ``state`` (of this world: checked by the caller) current; history restarts at it."""
        ctx = self.ctx
        from_tick = ctx.tick
        self.apply(state)
        ctx.history.clear()
        ctx.history.push(state)
        ctx.dirty = False
        ctx.emit("restore", from_tick=from_tick, **event)
        ctx.rolled_back(from_tick)

    # -- fork -----------------------------------------------------------------------------------------
    def fork_into(self, other: Context) -> None:
        """Make ``other`` (a new world's, empty, with this one's step and history settings) this world in
        its current state. It copies the state (the bus, each module's copy) and shares what never
        changes: the structure's layout, checks and copies (`rebind_structure`), the modules' parameter
        dicts, and what the modules share themselves (a MuJoCo core's compiled model, until either
        world changes a parameter)."""
        ctx = self.ctx
        records = ctx.structure.records
        refused = [r.name for r in records if not r.module.CAPABILITIES.can_fork]
        if refused:
            raise ForkError(f"fork refused: module(s) {', '.join(refused)} cannot fork")
        memo: dict[int, Any] = {}
        bindings = {rec.name: rec.module.bind_ports(None) for rec in records}  # copied unbound (`Module.fork`)
        clones: dict[str, Module] = {}
        try:
            for rec in records:
                clone = memo.get(id(rec.module))  # (a module another one holds is copied with it)
                clones[rec.name] = clone if clone is not None else rec.module.fork(memo)
        except BaseException:
            for clone in clones.values():  # free what was copied (FMU instances, processes)
                close_quietly(clone)
            raise
        finally:
            for rec in records:
                rec.module.bind_ports(bindings[rec.name])
        other.history.budget = ctx.history.budget  # a budget the scenario raised
        other.install(rebind_structure(ctx.structure, clones), carry_values=False, bus=ctx.buf)
        other.tick = ctx.tick
        other.scheduled = {k: list(v) for k, v in ctx.scheduled.items()}
        other.module_factory, other.rebuild = ctx.module_factory, ctx.rebuild
        other.core = clones.get(ctx.core.name) if ctx.core is not None else None  # type: ignore[assignment]
        other.known = {id(m): m for m in clones.values()}
