"""The ``threads`` backend of `Batch`: the branches of a world whose only module is a MuJoCo core,
rolled out by `mujoco.rollout` on threads of this process (the brain names it by class path:
`orchestrator.brain.batch`, so nothing above the modules imports MuJoCo). MuJoCo steps in C with the
GIL released: no Python per step.

A branch is `kernel.branch.run_branch` on the world, bit for bit, because each piece of it is made by the
core's own code or by the MuJoCo calls the core makes:

- start and parameters: the start is imported into a scratch fork of the world and the parameters
  are set there (`World.set`: the core applies them to its model); the branch rolls out on a copy of
  that model from that data's MuJoCo state (``mjSTATE_FULLPHYSICS``) and warm start. Each distinct
  start, and each distinct set of parameters, is prepared once per run;
- inputs: actuator controls (``core.ctrl``, ``core.<actuator>.ctrl``), joint forces (``core.joint_force``,
  ``core.<joint>.force``: ``qfrc_applied``) and free-body wrenches (``core.body_wrench``,
  ``core.<body>.wrench``: ``xfrc_applied``) become rollout's controls, one row per MuJoCo step (a tick
  of ``substeps`` steps holds its row); what is not driven keeps its bus value at the start, as in the
  world. Equality, mocap and user-data values ride along as constant controls (rollout resets them);
- timing: the core keeps its data "after mj_step1" (a tick is mj_step2, more steps, then mj_step1);
  rollout records after each whole mj_step. After tick k the world holds state k+1: joints and
  free-body positions are rollout's state row k (rows count MuJoCo steps: ``(k+1)*substeps - 1``),
  position- and velocity-stage sensors (the body velocities too) come from the next step's first
  half, sensordata row k+1, and acceleration-stage sensors from the step just taken, row k. The last
  tick's mj_step1 is made after the rollout, on the branch's own data, as the core makes it; the
  final state (integration state, warm start, sensor values) is read from that data;
- other body poses (orientations, bodies under joints) are MuJoCo's `mj_kinematics` (what mj_step1
  calls) of each recorded tick's positions on a scratch data: one C call per tick, paid only when
  such a pose is recorded;
- final states: set on the scratch fork with `World.restore` (the core's `set_state`) and exported
  there, so they are `World.export_state` bytes; ``keep_states=False`` skips this;
- a branch that diverges (MuJoCo counted a bad position, velocity or acceleration) or that rollout
  stopped early on another MuJoCo warning is run again on the scratch fork by `run_branch`: its
  failure, reason, tick, partial signals and rolled-back state are those of every other backend.

Refused before anything runs, saying what is supported: a world with any module besides the MuJoCo
core, connections, scenario events within the branches' ticks, the RK4 integrator (the core's
mj_step1/mj_step2 integrate it as Euler, mj_step does not), a core input it does not know, driving or
holding a body velocity input (it sets the state between steps), animated robots (a robot a selection
left out follows its ``joint_target`` between steps; without one that input has no effect, and is
not driven), recording what is not one of the core's ports.
"""

from __future__ import annotations

import copy
import os
import pickle
import threading
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.branch import BranchOutcome, BranchStatus, BranchTask, run_branch
from dynabrain.orchestrator.kernel.errors import DynabrainError, WiringError
from dynabrain.orchestrator.kernel.history import WorldState
from dynabrain.orchestrator.kernel.world import World

from .core import STATE, MujocoCore
from .rollout_map import (
    DRIVEN_BLOCKS,
    HELD_BLOCKS,
    INPUT_BLOCKS,
    OUTPUT_BLOCKS,
    SUPPORTED_INPUTS,
    SUPPORTED_RECORD,
    UNKNOWN,
    _Column,
    _Gather,
    _Ports,
    _Sources,
    refuse,
)
from .spec_source import VEL_PREFIX


@dataclass(frozen=True)
class _Start:
    """One start state with one set of parameter overrides, prepared on the scratch fork."""

    model: Any  # a copy of the core's model with the parameters applied
    sources: _Sources
    substeps: int
    state0: np.ndarray  # (1, nstate): mjSTATE_FULLPHYSICS
    warmstart0: np.ndarray  # (1, nv)
    spec: int  # rollout's control_spec
    user: np.ndarray  # the start's values of ``spec`` (ctrl and forces are overwritten per step)
    mocap: tuple[np.ndarray, np.ndarray]  # for the kinematics of recorded poses
    bus: dict[str, np.ndarray]  # every block's value on the bus at the start, flat
    snapshot: WorldState  # the scratch fork at the start with the parameters set
    edits: Any


@dataclass(frozen=True)
class _Base:
    """One distinct start state, imported into the scratch fork and checked."""

    snapshot: WorldState
    bus: dict[str, np.ndarray]  # every block's value on the bus, flat
    sources: _Sources


@dataclass
class _Job:
    task: BranchTask
    start: _Start
    control: np.ndarray | None  # (1, nstep, ncontrol)
    inputs: dict[str, np.ndarray]  # each input block of the core per tick, (ticks, size)


@dataclass
class _Rolled:
    job: _Job
    signals: dict[str, np.ndarray] | None  # None: run it again with run_branch (it diverged or stopped)
    state: np.ndarray | None = None  # the core's integration state after the last tick
    sensors: np.ndarray | None = None  # ... and its sensor values


class RolloutBackend:
    """``workers`` threads, each rolling out one branch at a time with `mujoco.rollout` on a MjData
    of its own. Same interface as `pool.ProcessPool`: `map(tasks)` and `close()`."""

    def __init__(self, world: World, workers: int | None = None):
        self.world = world
        self._check_world(world)
        self.workers = workers or os.cpu_count() or 1
        self._executor = ThreadPoolExecutor(self.workers, thread_name_prefix="dynabrain-rollout")
        self._local = threading.local()
        self._scratch: World | None = None
        self._sources: dict[Any, _Sources] = {}
        self.reran = 0
        """Branches run again on the scratch fork (diverged, or stopped by a MuJoCo warning) so far."""

    # -- checks -----------------------------------------------------------------------------------------
    def _check_world(self, world: World) -> Any:
        core = world.core
        if not isinstance(core, MujocoCore):
            kind = "no physics core" if core is None else f"a {type(core).__name__} core"
            raise refuse(f"it rolls out MuJoCo cores with mujoco.rollout; world {world.name!r} has {kind}")
        others = sorted(name for name in world.modules if name != core.name)
        if others:
            raise refuse(f"it runs worlds whose only module is the MuJoCo core; world {world.name!r} also has "
                         f"{', '.join(others)} (their steps are Python): use backend 'processes' or 'serial'")
        if world.connections:
            conns = ", ".join(f"{c.src} -> {c.dst}" for c in world.connections)
            raise refuse(f"it drives the core open loop; world {world.name!r} connects {conns}")
        unknown = [f"{core.name}.{b}" for b in _Ports(core).inputs if b not in INPUT_BLOCKS]
        if unknown:
            raise refuse(f"the core has input(s) {', '.join(unknown)}, which it cannot map onto mujoco.rollout; it "
                         f"drives {SUPPORTED_INPUTS}")
        if core.mj.model.opt.integrator == int(mujoco.mjtIntegrator.mjINT_RK4):
            raise refuse("the core's integrator is RK4, which the core's mj_step1/mj_step2 integrate as Euler and "
                         "mj_step does not; it supports Euler, implicit and implicitfast")
        return core

    def _check_events(self, world: World, first: int, ticks: int) -> None:
        scheduled = [t for t in world.scheduled_ticks() if first <= t < first + ticks]
        if scheduled:
            raise refuse(f"the world has scenario events at ticks {', '.join(map(str, scheduled[:5]))}, within the "
                         f"branches' ticks {first}..{first + ticks - 1}; it steps MuJoCo alone (use 'serial' or "
                         "'processes')")

    def _plan(self, ports: _Ports, tasks: Sequence[BranchTask]) -> dict[str, _Column]:
        """Every input and recorded name as columns of a block, or a refusal naming it."""
        world, columns = self.world, {}
        for name in {n for t in tasks for n in t.inputs}:
            full = world.settable(name)
            col = ports.column(full) if isinstance(full, str) else None
            if col is None or col.block not in DRIVEN_BLOCKS:
                raise WiringError(f"batch backend 'threads' cannot drive {name!r}: it drives {SUPPORTED_INPUTS}"
                                  + (" (a velocity input sets the state between MuJoCo steps)"
                                     if col is not None and col.block in HELD_BLOCKS else ""))
            columns[name] = col
        signals = set(world.signals)
        for name in {n for t in tasks for n in t.record}:
            full = name if name in signals else f"{ports.core}.{name}"
            col = ports.column(full) if full in signals else None
            if col is None or col.block not in (*OUTPUT_BLOCKS, *INPUT_BLOCKS):
                raise WiringError(f"batch backend 'threads' cannot record {name!r}: it records {SUPPORTED_RECORD}")
            columns[name] = col
        return columns

    # -- running ------------------------------------------------------------------------------------------
    def map(self, tasks: Sequence[BranchTask]) -> list[BranchOutcome]:
        """Every task's outcome, in the order of ``tasks``. Everything that can refuse the request is
        checked first; then each branch is handed to the threads as soon as it is prepared, and its
        final state exported as soon as it is rolled out."""
        core = self._check_world(self.world)
        ports = _Ports(core)
        columns = self._plan(ports, tasks)
        self.prepare()
        longest: dict[bytes, int] = {}  # each distinct start: the most ticks a branch runs from it
        for task in tasks:
            longest[task.start] = max(task.ticks, longest.get(task.start, 0))
        bases: dict[bytes, _Base | None] = {}  # each distinct start, imported into the scratch fork
        for task in tasks:
            if task.start not in bases:
                bases[task.start] = self._import(task, longest[task.start], ports, columns)
        starts: dict[Any, _Start | None] = {}  # each distinct start with each distinct set of parameters
        pending: set[Future] = set()
        outcomes: dict[int, BranchOutcome] = {}
        refused: list[BranchTask] = []  # by the scratch fork (a bad state or parameter): `run_branch` fails them
        try:
            for task in tasks:
                key = (task.start, tuple((n, pickle.dumps(v)) for n, v in task.params.items()))
                if key not in starts:
                    base = bases[task.start]
                    starts[key] = None if base is None else self._prepare(base, task, columns)
                start = starts[key]
                if start is None:
                    refused.append(task)
                    continue
                pending.add(self._executor.submit(self._roll, self._job(task, start, ports, columns), columns))
                self._collect({f for f in pending if f.done()}, pending, outcomes)
            while pending:
                self._collect(wait(pending, return_when="FIRST_COMPLETED").done, pending, outcomes)
        finally:
            for future in pending:
                future.cancel()
        for task in refused:
            outcomes[task.index] = run_branch(self._scratch, task)
        return [outcomes[t.index] for t in tasks]

    def _collect(self, done: set[Future], pending: set[Future], outcomes: dict[int, BranchOutcome]) -> None:
        for future in done:
            pending.discard(future)
            rolled = future.result()
            outcomes[rolled.job.task.index] = self._finish(rolled)

    def prepare(self) -> None:
        """Make the scratch fork (a copy of the world, read now: before a batch runs on another thread)."""
        if self._scratch is None:
            self._scratch = self.world.fork(self.world.name)

    def _import(self, task: BranchTask, ticks: int, ports: _Ports, columns: dict[str, _Column]) -> _Base | None:
        """The scratch fork at the start of ``task``, checked (the core alone, no events in the ``ticks``
        the longest branch from it runs, no velocity input held, recorded sensors of a known stage); None
        when the fork refuses the state (`run_branch` then fails the branch, as on every backend)."""
        scratch = self._scratch
        assert scratch is not None
        try:
            scratch.import_state(task.start)
        except DynabrainError:
            return None
        view = self._check_world(scratch).mj
        self._check_events(scratch, scratch.tick_count, ticks)
        edits = view.edits
        animated = sorted(f.object for f in edits.frozen
                          if getattr(f, "animated", False) and f.object not in edits.absent)
        if animated:
            raise refuse(f"robot(s) {', '.join(animated)} are animated (left out by a selection, they follow their "
                         "joint targets between MuJoCo steps, which mujoco.rollout cannot); use backend 'serial' or "
                         "'processes'")
        bus = {b: np.asarray(scratch.get(f"{ports.core}.{b}"), dtype=np.float64).reshape(-1) for b in ports.sizes}
        held = [f"{ports.core}.{b}" for b in HELD_BLOCKS if b in bus and not np.isnan(bus[b]).all()]
        if held:
            raise refuse(f"the start holds a value in {', '.join(held)} (a velocity input sets the state between "
                         "MuJoCo steps, which mujoco.rollout cannot); use backend 'serial' or 'processes'")
        sources = self._sources.get(view.edits)
        if sources is None:
            sources = self._sources[view.edits] = _Sources(view.model, ports, VEL_PREFIX)
        unknown = [n for n in task.record if columns[n].block == "sensordata" and (
            sources.kind["sensordata"][columns[n].start:columns[n].start + columns[n].size] == UNKNOWN).any()]
        if unknown:
            raise refuse(f"cannot tell when MuJoCo computes {', '.join(unknown)} (a sensor of no known stage); it "
                         "records position-, velocity- and acceleration-stage sensors")
        return _Base(scratch.snapshot(), bus, sources)

    def _prepare(self, base: _Base, task: BranchTask, columns: dict[str, _Column]) -> _Start | None:
        """The start of ``task`` with its parameters, set on the scratch fork by the core itself (on a copy
        of its model); None when a parameter is refused (`run_branch` then fails the branch)."""
        scratch = self._scratch
        assert scratch is not None
        try:
            scratch.restore(base.snapshot)
            for name, value in task.params.items():
                scratch.set(name, value)
        except DynabrainError:
            return None
        core = scratch.core
        view = core.mj
        model, data = copy.copy(view.model), view.data
        full = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
        state0 = np.empty((1, mujoco.mj_stateSize(model, full)))
        mujoco.mj_getState(model, data, state0[0], full)
        spec = self._spec(model, base.sources, base.bus, task, columns)
        user = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, user, spec)
        return _Start(model, base.sources, int(core.params["substeps"]), state0, data.qacc_warmstart.copy()[None],
                      spec, user, (data.mocap_pos.copy(), data.mocap_quat.copy()), base.bus,
                      scratch.snapshot() if task.params else base.snapshot, view.edits)

    @staticmethod
    def _spec(model: Any, sources: _Sources, bus: dict[str, np.ndarray], task: BranchTask,
              columns: dict[str, _Column]) -> int:
        """Rollout's control_spec: each driven input block that is driven or not zero on the bus, and what
        rollout would otherwise reset (equality activations, mocap poses, user data) as constants."""
        s, spec = mujoco.mjtState, 0
        driven = {columns[n].block for n in task.inputs}
        for block, (bit, _, _, _) in sources.routes.items():
            if block == "ctrl" or block in driven or bus[block].any():
                spec |= bit
        constants = ((model.neq, s.mjSTATE_EQ_ACTIVE), (model.nmocap, s.mjSTATE_MOCAP_POS | s.mjSTATE_MOCAP_QUAT),
                     (model.nuserdata, s.mjSTATE_USERDATA))
        for count, bits in constants:
            if count:
                spec |= int(bits)
        return spec

    def _job(self, task: BranchTask, start: _Start, ports: _Ports, columns: dict[str, _Column]) -> _Job:
        """The branch's input blocks per tick (the start's bus values, then its inputs in order, as
        `World.run` writes them) and rollout's controls from them (a tick's row held for its substeps)."""
        ticks, nsub, model = task.ticks, start.substeps, start.model
        blocks = {b: np.broadcast_to(start.bus[b], (ticks, ports.sizes[b])).copy() for b in ports.inputs}
        for name, values in task.inputs.items():
            col = columns[name]
            blocks[col.block][:, col.start:col.start + col.size] = np.asarray(values).reshape(ticks, col.size)
        if not start.spec:
            return _Job(task, start, None, blocks)
        control = np.empty((1, ticks * nsub, start.user.size))
        control[0] = start.user
        for block, (bit, width, src, dst) in start.sources.routes.items():
            if start.spec & bit:
                at = mujoco.mj_stateSize(model, start.spec & (bit - 1))
                values = np.zeros((ticks, width))
                values[:, dst] = blocks[block][:, src]
                control[0, :, at:at + width] = values if nsub == 1 else np.repeat(values, nsub, axis=0)
        return _Job(task, start, control, blocks)

    # -- on a worker thread -----------------------------------------------------------------------------------
    def _thread_data(self, start: _Start) -> tuple[Any, Any, Any]:
        """This thread's rollout (no pool of its own), and its MjData for the start's structure (two: one
        rolls out, one computes kinematics)."""
        from mujoco import rollout

        local = self._local
        if not hasattr(local, "rollout"):
            local.rollout, local.data = rollout.Rollout(nthread=0), {}
        pair = local.data.get(start.edits)
        if pair is None:
            pair = local.data[start.edits] = (mujoco.MjData(start.model), mujoco.MjData(start.model))
        return local.rollout, *pair

    def _roll(self, job: _Job, columns: dict[str, _Column]) -> _Rolled:
        start, task = job.start, job.task
        runner, data, kin = self._thread_data(start)
        model, nsub, ticks = start.model, start.substeps, task.ticks
        nstep = ticks * nsub
        state = np.empty((1, nstep, start.state0.shape[1]))
        sensing = any(columns[n].block in ("sensordata", "body_linvel", "body_angvel") for n in task.record)
        sensordata = np.empty((1, nstep, model.nsensordata)) if sensing and model.nsensordata else None
        runner.rollout([model], [data], start.state0, job.control, control_spec=start.spec, skip_checks=True,
                       nstep=nstep, initial_warmstart=start.warmstart0, state=state, sensordata=sensordata)
        mujoco.mj_step1(model, data)  # the end of the last tick, as the core makes it
        w = mujoco.mjtWarning
        bad = sum(data.warning[int(k)].number for k in (w.mjWARN_BADQACC, w.mjWARN_BADQVEL, w.mjWARN_BADQPOS))
        stopped = nstep > 1 and state[0, -1, 0] == state[0, -2, 0]  # rollout stops on a warning: time stands
        if bad or stopped:
            return _Rolled(job, None)
        final = np.empty(mujoco.mj_stateSize(model, STATE))
        mujoco.mj_getState(model, data, final, STATE)
        signals = _Gather(job, state[0], None if sensordata is None else sensordata[0], data, kin).signals(columns)
        n = start.sources.n_own_sensordata  # the core saves the acceleration-stage ones with its state
        return _Rolled(job, signals, final, data.sensordata[:n].copy() if n else None)

    # -- back on the calling thread ---------------------------------------------------------------------------
    def _finish(self, rolled: _Rolled) -> BranchOutcome:
        task = rolled.job.task
        scratch = self._scratch
        assert scratch is not None
        if rolled.signals is None:
            self.reran += 1
            return run_branch(scratch, task)
        state = self._export(rolled) if task.keep_state else None
        return BranchOutcome(task.index, rolled.signals, state, BranchStatus(True, ticks_done=task.ticks))

    def _export(self, rolled: _Rolled) -> bytes:
        """The branch's final state as `World.export_state` bytes, made on the scratch fork: the start's
        bus and parameters with the core set to the final MuJoCo state (its `set_state` rewrites the
        outputs), then the inputs as the last tick left them on the bus."""
        job, scratch = rolled.job, self._scratch
        assert scratch is not None
        start = job.start.snapshot
        (edits, _, _), = start.states  # the core's state: (edits, integration state, sensor values)
        scratch.restore(WorldState(start.world_id, start.tick + job.task.ticks, start.structure, start.bus,
                                   ((edits, rolled.state, rolled.sensors),), start.params))
        for name, values in job.task.inputs.items():
            scratch.set(name, np.asarray(values)[-1])
        return scratch.export_state()

    def close(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)
        if self._scratch is not None:
            self._scratch.close()
            self._scratch = None
