"""The ``lockstep`` backend: N branches of one world in this process, advanced tick by tick together.

Each branch has a world of its own (a fork, kept from one batch to the next) in its start state with
its parameters set; for the batch, every branch's modules are bound to one row of a stacked bus (an
``(N, bus)`` array), so that a tick is the structure's schedule walked once for all N:

- the inputs given per tick are written into each branch's row (one numpy assignment per input when
  every branch is running);
- each connection's copy is one copy across the rows (``bus[:, dst] = bus[:, src]``);
- each module is stepped once for all branches through its class's `Module.step_batch`, or the
  physics' (below): the MuJoCo core steps the N physics in one call with the GIL released, the robot
  modules that implement it compute all branches with numpy, and a module without it is stepped
  branch by branch (the default `step_batch`);
- the outputs are checked finite per branch, and the signals asked for recorded from the rows.

A branch is `branch.run_branch` on its world, bit for bit: the same calls on the same states in the
same order (each module's step, or its batched step, which makes each row what the member's own step
makes), with the same time; the final state is exported from the branch's world, from its row of the
bus and its modules' states. Nothing of history is kept while the branches run: a branch that fails (a
module raised for it, its physics diverged, an output is not finite) leaves the lockstep at once and
is run again alone, from its start, by `run_branch` on its world (every branch stepped by a batched
step that raised, since it does not say for which), so its failure, reason, tick, partial
signals and rolled-back state are those of every other backend; the others go on.

Branches are stepped together when their worlds have the same structure (modules, ports, periods,
connections) at the same tick; branches that start from states of other structures or ticks (an edit
inside a branch) are stepped in a lockstep group of their own, and a branch whose ticks run into one
of the world's scheduled events is run alone by `run_branch` (events are not stepped in lockstep);
`notes` says so for each batch (`BatchResult.notes`).

The MuJoCo cores' physics (`PHYSICS`, ``physics=`` or ``DYNABRAIN_LOCKSTEP_PHYSICS``): by default MuJoCo's
own batch (``mjbatch``: `modules.mujoco.mjbatch`, bit for bit; the core, the sensors and the ZMP of every
branch read from its arrays), where the group allows it, else each branch's MjData stepped on threads
(``threads``: `modules.mujoco.batched`); or MJWarp (``mjwarp``: `modules.mujoco.warp_batch`, on warp's CPU
device unless told otherwise; close to C, not bit for bit: a branch run again alone runs on C).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..kernel.branch import BranchOutcome, BranchTask, run_branch
from ..kernel.errors import DynabrainError
from ..kernel.history import WorldState
from ..kernel.module import Module
from ..kernel.world import World
from .lockstep_group import LockstepGroup

PHYSICS = {"auto": "dynabrain.modules.mujoco.mjbatch", "mjbatch": "dynabrain.modules.mujoco.mjbatch",
           "threads": None, "mjwarp": "dynabrain.modules.mujoco.warp_batch"}
"""The physics a lockstep batch may step its MuJoCo cores with: by name, the module (resolved when asked,
so the brain imports no shipped module) that replaces a core class's own batched step, in one of two ways:

- ``open(entries)`` (MuJoCo's own batch, ``mjbatch``): for a group, a session that steps the
  core and the modules that read it (``session.handles(name)``, ``session.step_batch(name, ...)``,
  ``session.sync(rows)`` before an ending branch's states are read, ``session.close()``), or a sentence
  saying why it declines the group (stepped then by the classes' own batched steps);
- ``handles(cls)`` and ``step_batch(cls, ...)`` (``mjwarp``).

None: the classes' own (MuJoCo's C on threads). ``auto`` (the default) is ``mjbatch`` where MuJoCo has
it and the group allows it, else the classes' own, silently."""


def _physics(name: str | None) -> tuple[str, Any]:
    name = name or os.environ.get("DYNABRAIN_LOCKSTEP_PHYSICS", "").strip() or "auto"
    if name not in PHYSICS:
        raise DynabrainError(f"batch backend 'lockstep': no physics {name!r} (one of {', '.join(PHYSICS)})")
    if PHYSICS[name] is None:
        return name, None
    physics = importlib.import_module(PHYSICS[name])
    why = physics.unavailable()
    if why is not None:
        if name == "auto":
            return name, None
        raise DynabrainError(f"batch backend 'lockstep': physics {name!r} cannot run here: {why}")
    return name, physics


@dataclass
class _Branch:
    """A branch of a lockstep group: its task, its world (in its start state, parameters set), the
    snapshot of that start, and its row of the group's bus."""

    task: BranchTask
    world: World
    start: WorldState
    fork: int


class LockstepBackend:
    """The ``lockstep`` backend of `Batch` (see the module docstring). ``workers``: what `Batch.parallelism`
    says (default: every core); the physics threads are the MuJoCo core's (`modules.mujoco.batched.workers`:
    every core, or ``DYNABRAIN_LOCKSTEP_THREADS``)."""

    def __init__(self, world: World, workers: int | None = None, physics: str | None = None):
        self.world = world
        self.physics_name, self.physics = _physics(physics)  # see `PHYSICS`
        self.size = workers or os.cpu_count() or 1
        self._scratch: World | None = None
        self._forks: list[World] = []
        self._ended: dict[int, tuple[bytes, WorldState, int]] = {}  # `_continuing`
        # the stacked bus, one row per fork, for one layout; the forks whose modules are bound to their
        # row of it, with the bindings their world gave them (`_own` gives those back)
        self._bus: np.ndarray | None = None
        self._ro: np.ndarray | None = None
        self._layout: Any = None
        self._kept: dict[int, list[tuple[Module, Any]]] = {}
        self._sessions: dict[tuple[int, ...], Any] = {}  # the forks of a group -> its physics' last session
        self.notes: list[str] = []
        """What the last batch did other than one lockstep over every branch (groups, branches run alone)."""
        self.reran = 0
        """Branches run again alone after they failed in lockstep (all batches)."""

    def prepare(self) -> None:
        """Make the private copy of the world the branches' worlds are forked from (read now: before a
        batch runs on another thread)."""
        if self._scratch is None:
            self._scratch = self.world.fork(self.world.name)

    def map(self, tasks: Sequence[BranchTask]) -> list[BranchOutcome]:
        self.prepare()
        assert self._scratch is not None
        while len(self._forks) < len(tasks):
            self._forks.append(self._scratch.fork(self.world.name))
        self.notes = []
        outcomes: dict[int, BranchOutcome] = {}
        groups: dict[tuple, list[_Branch]] = {}
        placed = self._continuing(tasks)
        self._ended = {}
        for task, (fork, going_on) in zip(tasks, placed, strict=True):
            world = self._forks[fork]
            if going_on is not None:
                start = going_on
            else:
                self._own(fork)
                try:
                    world.import_state(task.start)
                    for name, value in task.params.items():
                        world.set(name, value)
                except DynabrainError:  # refused: it fails as it would on any backend
                    outcomes[task.index] = run_branch(world, task)
                    continue
                start = world.snapshot()
            if any(start.tick <= t < start.tick + task.ticks for t in world.scheduled_ticks()):
                self._own(fork)
                self.notes.append(f"branch {task.index} runs into a scheduled event: run alone")
                outcomes[task.index] = run_branch(world, task)
                continue
            if world.loops():  # a loop iterated to agreement (kernel/iterate.py) is one schedule entry: not batched
                self._own(fork)
                self.notes.append(f"branch {task.index}: its world iterates a loop ({', '.join(world.loops())}): "
                                  "run alone")
                outcomes[task.index] = run_branch(world, task)
                continue
            groups.setdefault(_group_key(start), []).append(_Branch(task, world, start, fork))
        if len(groups) > 1:
            self.notes.append(f"the branches start from {len(groups)} structures or ticks: stepped as "
                              f"{len(groups)} lockstep groups of " + ", ".join(str(len(g)) for g in groups.values())
                              + " branches")
        for group in groups.values():
            done, failed = self._run(sorted(group, key=lambda b: b.fork))
            for index, (outcome, final, fork) in done.items():
                outcomes[index] = outcome
                if outcome.state is not None:
                    self._ended[id(outcome.state)] = (outcome.state, final, fork)
            for branch in failed:
                self.reran += 1
                self._own(branch.fork)
                outcomes[branch.task.index] = run_branch(branch.world, branch.task)
            if failed:
                self.notes.append(f"branch(es) {', '.join(str(b.task.index) for b in failed)} failed in lockstep: "
                                  "run again alone, from their start")
        return [outcomes[t.index] for t in tasks]

    def _run(self, group: list[_Branch]) -> tuple[dict[int, tuple[BranchOutcome, WorldState, int]], list[_Branch]]:
        """Step a group (its branches in fork order). When its forks are a run of neighbours, their rows
        of the backend's stacked bus are the group's bus, and their modules stay bound there after the
        batch (the next batch that goes on from its ends binds nothing); otherwise the group has a bus of
        its own, bound for this batch only."""
        forks = [b.fork for b in group]
        layout = group[0].start.structure.layout
        if forks != list(range(forks[0], forks[0] + len(forks))):
            bus = np.empty((len(group), layout.size))
            ro = _read_only(bus)
            kept = [pair for row, b in enumerate(group) for pair in _bind(b, bus[row], ro[row])]
            try:
                return self._lockstep(group, bus, ro)
            finally:
                _give_back(kept)
        if self._layout is not layout or self._bus is None or len(self._bus) < len(self._forks):
            for fork in list(self._kept):
                self._own(fork)
            self._bus = np.empty((len(self._forks), layout.size))
            self._ro, self._layout = _read_only(self._bus), layout
        for b in group:
            if b.fork not in self._kept:
                self._kept[b.fork] = _bind(b, self._bus[b.fork], self._ro[b.fork])
        lo, hi = forks[0], forks[-1] + 1
        return self._lockstep(group, self._bus[lo:hi], self._ro[lo:hi])

    def _lockstep(self, group: list[_Branch], bus: np.ndarray, ro: np.ndarray) -> tuple[dict, list[_Branch]]:
        key = tuple(b.fork for b in group)
        previous = self._sessions.pop(key, None)
        step = LockstepGroup(group, self.world.dt_ns, bus, ro, self.physics, previous)
        try:
            return step.run()
        finally:
            if previous is not None and step.session is not previous:
                previous.close()
            if step.session is not None:
                self._sessions[key] = step.session
            if step.declined and self.physics_name not in ("auto", "threads"):
                self.notes.append(f"physics {self.physics_name!r} declined the branches: {step.declined}; "
                                  "stepped on threads")

    def _own(self, fork: int) -> None:
        """Give fork ``fork``'s modules back the bindings of its world (before it imports or runs alone)."""
        kept = self._kept.pop(fork, None)
        if kept is not None:
            _give_back(kept)

    def _continuing(self, tasks: Sequence[BranchTask]) -> list[tuple[int, WorldState | None]]:
        """For each task, the fork it runs on and, when it goes on from where that fork's branch of the
        last batch ended (its start is that branch's final state, the very bytes returned, and it sets no
        parameter: a vector env's next step, a plan going on), that end as its start: the fork's modules
        are in it already, so nothing is imported. The others take the forks left over."""
        claimed: dict[int, int] = {}  # task position -> fork
        for k, task in enumerate(tasks):
            hit = self._ended.get(id(task.start))
            if hit is not None and hit[0] is task.start and not task.params and hit[2] not in claimed.values():
                claimed[k] = hit[2]
        free = iter(f for f in range(len(self._forks)) if f not in set(claimed.values()))
        out = []
        for k in range(len(tasks)):
            if k in claimed:
                out.append((claimed[k], self._ended[id(tasks[k].start)][1]))
            else:
                out.append((next(free), None))
        return out

    def close(self) -> None:
        for session in self._sessions.values():
            session.close()
        self._sessions = {}
        for fork in list(self._kept):
            self._own(fork)
        for world in self._forks:
            world.close()
        self._forks = []
        if self._scratch is not None:
            self._scratch.close()
            self._scratch = None


def _read_only(bus: np.ndarray) -> np.ndarray:
    ro = bus.view()
    ro.flags.writeable = False
    return ro


def _bind(branch: _Branch, row: np.ndarray, ro: np.ndarray) -> list[tuple[Module, Any]]:
    """Bind the branch's modules to ``row`` of a stacked bus (``ro``: the row read-only), as its world
    binds them to its own bus; returns each module with the binding its world gave it."""
    kept = []
    layout = branch.start.structure.layout
    for rec in branch.start.structure.records:
        old = rec.module.binding
        rec.module.bind_ports(layout.modules[rec.name].binding(row, ro, old.param_changed if old is not None else None))
        kept.append((rec.module, old))
        rec.module.bind()
    return kept


def _give_back(kept: list[tuple[Module, Any]]) -> None:
    for module, old in kept:
        module.bind_ports(old)
        module.bind()


def _group_key(start: WorldState) -> tuple:
    """What branches must share to be stepped together: the layout of the bus (shared by a world and
    its forks), the connections, each module's class, period and phase, and the tick."""
    structure = start.structure
    return (id(structure.layout), structure.connections, start.tick,
            tuple((type(r.module), r.period_ns, r.phase) for r in structure.records))
