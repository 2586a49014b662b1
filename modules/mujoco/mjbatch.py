"""MuJoCo's own batch (`mujoco.batch`, MuJoCo 4.0) as the physics of a lockstep batch: the N branches'
cores, and the modules that read them, stepped as arrays with a leading branch axis.

`mujoco.batch.Batch` keeps many simulations of one model in state rows, steps them on its own thread pool
in one call (the GIL released), and copies the derived fields it is asked for (``xpos``, ``sensordata``,
...) into ``(branches, ...)`` arrays after each call. In a persistent batch (one MjData per simulation) a
step goes on from the stages the last call computed: ``step(stage=mjSTAGE_VEL)`` is `mj_step2`, the
substeps' `mj_step`, then the stages `mj_step1` computes, which are the calls of `MujocoCore.step`, so a
branch's physics is bit for bit the same (`tests/test_batch_lockstep.py` checks it against serial).

What a tick does here instead of N steps of each module:

- the core: its inputs (joint forces, motor controls, wrenches) written into the state rows of every
  branch with one numpy assignment per copy of `MujocoCore.copies`, one `Batch.step` call, the
  divergence counters compared as an array, and its outputs gathered from the batch's arrays;
- the sensors (`modules.sensors`) on their fast path (no delay, no noise): one gather each from the
  batch's ``sensordata``, ``qpos`` or ``qvel``;
- the ZMP sensor: its contact values gathered for every branch at once, then its own geometry per branch.

No branch's MjData is touched while the branches run; a branch's data is written back from the batch
(`Session.sync`) when it ends, before its states are read. Where this cannot be bit for bit the core's
own step, `open` declines the group (the lockstep then steps it on threads, `modules.mujoco.batched`):
another module reads the core's data (a camera, a pushing probe, a sensor with delay or noise), the core
animates a robot (Python between the halves of its step), or more than one core is in the world. A branch
whose velocity input holds a value at a tick, or whose physics diverges or raises in MuJoCo, fails in
the lockstep and is run again alone (so it fails, or not, exactly as it would there).

Measured (`bench/predict.py`, the humanoid with its 8 modules, 64 branches x 500 ticks, 2 cores): see
bench/README.md; `Batch.step` alone on the core-only humanoid runs at 0.97 of `mujoco.rollout`'s speed
over the same ticks (one call a tick against one call for all 500).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.errors import PhysicsDivergedError

from . import batched
from .access import MujocoLink, contiguous
from .compiled import MujocoView
from .core import MujocoCore

try:
    from mujoco import batch as _mjbatch
except ImportError:  # MuJoCo before 4.0
    _mjbatch = None  # type: ignore[assignment]

_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
_VEL = int(mujoco.mjtStage.mjSTAGE_VEL)
_DIVERGED = slice(int(mujoco.mjtWarning.mjWARN_BADQPOS), int(mujoco.mjtWarning.mjWARN_BADQACC) + 1)
assert _DIVERGED.stop - _DIVERGED.start == 3 and int(mujoco.mjtWarning.mjWARN_BADQVEL) == _DIVERGED.start + 1
_STATE_FIELDS = ("qpos", "qvel", "ctrl", "qfrc_applied", "xfrc_applied")
"""The fields the batch keeps in its state rows (its arrays of them are the rows: a write is the state)."""
_FIELDS = (*_STATE_FIELDS, "xpos", "xquat", "sensordata")
"""The MjData fields the core's copies and the sensors' reads may name."""


def unavailable() -> str | None:
    """Why this physics cannot run here, or None."""
    return None if _mjbatch is not None else f"MuJoCo {mujoco.__version__} has no mujoco.batch (4.0 or later)"


def _address(a: np.ndarray) -> int:
    return int(a.__array_interface__["data"][0])


def _positions(view: np.ndarray, base: np.ndarray) -> np.ndarray | None:
    """The positions in ``base`` (a contiguous float64 array, taken flat) of each element of ``view``
    (in its C order), or None when ``view`` does not lie in ``base``."""
    if view.dtype != np.float64 or base.dtype != np.float64 or not base.flags.c_contiguous:
        return None
    start = _address(view) - _address(base)
    if start < 0 or start % 8 or start // 8 + (view.size and 1) > base.size:
        return None
    if view.size == 0:
        return np.zeros(0, dtype=np.intp)
    index = np.full(view.shape, start // 8, dtype=np.intp)
    for axis, (n, stride) in enumerate(zip(view.shape, view.strides, strict=True)):
        shape = [1] * view.ndim
        shape[axis] = n
        index = index + (np.arange(n, dtype=np.intp) * (stride // 8)).reshape(shape)
    flat = index.reshape(-1)
    return flat if flat.max(initial=0) < base.size and flat.min(initial=0) >= 0 else None


def _field(data: mujoco.MjData, view: np.ndarray) -> tuple[str, np.ndarray] | None:
    """Which of the data's fields (`_FIELDS`) ``view`` lies in, and its positions there (flat)."""
    for name in _FIELDS:
        base = getattr(data, name)
        where = _positions(view, base.reshape(-1))
        if where is not None:
            return name, where
    return None


def _pick(index: Any, n: int) -> np.ndarray:
    return np.arange(n, dtype=np.intp)[index]


def _reads_core(module: Any, core: Any) -> bool:
    """Whether a module holds the core, a link to it, MuJoCo's model or data, or an array lying in the
    core's data (so may read the core's MjData as it steps, which this physics does not keep current)."""
    data = core._compiled.data
    for v in vars(module).values():
        if v is core or isinstance(v, (MujocoLink, MujocoView, mujoco.MjData, mujoco.MjModel)):
            return True
        if isinstance(v, np.ndarray) and v.dtype == np.float64 and _field(data, v) is not None:
            return True
    return False


def open(entries: Sequence[tuple[str, list[Any]]], previous: Session | None = None) -> Session | str:
    """A session stepping a lockstep group's core and the modules that read it (``entries``: each
    schedule entry's name and members, one per branch, in row order), or why not (a sentence).
    ``previous``: this group's session of the last batch, taken again (states loaded anew) when it
    fits these members (a vector env's next step makes no batch of MuJoCo's again: 0.7 ms saved)."""
    why = unavailable()
    if why is not None:
        return why
    cores = [(name, members) for name, members in entries if isinstance(members[0], MujocoCore)]
    if len(cores) != 1:
        return f"the world has {len(cores)} MuJoCo cores; this physics steps one"
    core_name, core_members = cores[0]
    first = core_members[0]
    if type(first).step is not MujocoCore.step or type(first).step_batch.__func__ is not MujocoCore.step_batch.__func__:
        return f"core {core_name!r} ({type(first).__name__}) steps in its own way"
    if any(c._compiled.anim is not None for c in core_members):
        return f"core {core_name!r} animates a robot (Python between the halves of its step)"
    from dynabrain.modules.sensors import Sensor  # (here: the sensors import this package)
    from dynabrain.modules.zmp import ZmpSensor

    readers: dict[str, str] = {}
    for name, members in entries:
        if name == core_name:
            continue
        m0 = members[0]
        if isinstance(m0, Sensor) and type(m0).step is Sensor.step and type(m0)._sample is Sensor._sample:
            for m in members:  # what their step does first: ids found again on a new core (a fork's)
                if m._link.core.mj is not m._link.seen:
                    m._link.changed()
                    m._resolve()
                    m._plan()
            slow = [k for k, m in enumerate(members) if not m._fast or m._link.core is not core_members[k]]
            if slow:
                return (f"sensor {name!r} has a delay or noise in branch(es) {', '.join(map(str, slow[:5]))} "
                        "(its own step reads the core's data)")
            readers[name] = "sensor"
        elif type(m0) is ZmpSensor:
            if any(m._link.core is not core_members[k] for k, m in enumerate(members)):
                return f"ZMP sensor {name!r} reads another core"
            readers[name] = "zmp"
        elif _reads_core(m0, first):
            return f"module {name!r} ({type(m0).__name__}) reads the core's data as it steps"
    members = {n: m for n, m in entries if n in readers}
    if previous is not None and previous.fits(core_name, core_members, members):
        previous.load()
        return previous
    try:
        return Session(core_name, core_members, members, readers)
    except RuntimeError as exc:  # a copy this physics cannot make from its arrays: the group steps on threads
        return str(exc)


class Session:
    """One lockstep group's physics on a `mujoco.batch.Batch` (see the module docstring)."""

    def __init__(self, core_name: str, cores: list[Any], readers: dict[str, list[Any]], kinds: dict[str, str]):
        self.core_name, self.cores, self.kinds = core_name, cores, dict(kinds)
        self.kinds[core_name] = "core"
        self.count = n = len(cores)
        first = cores[0]._compiled
        self.model = first.model
        self.nsub = cores[0]._nsub
        self.batch = _mjbatch.Batch(self.model, n, nthread=min(batched.workers(), n), persistent=True)
        self.scenes = [c._compiled for c in cores]
        self.readers = {name: list(members) for name, members in readers.items()}
        self.load()
        data = first.data
        ins, outs = cores[0].copies()
        self.ins = [self._plan_in(data, cores[0], dst, di, src, si) for dst, di, src, si in ins]
        self.outs = [self._plan_out(data, cores[0], dst, di, src, si) for dst, di, src, si in outs]
        vel = _positions(cores[0]._vel, cores[0].inp_flat) if cores[0]._vel.size else None
        self.vel = contiguous(vel) if vel is not None else None
        self.rows: dict[str, dict[int, int]] = {core_name: {id(c): k for k, c in enumerate(cores)}}
        self.reads: dict[str, Any] = {}
        for name, members in readers.items():
            self.rows[name] = {id(m): k for k, m in enumerate(members)}
            self.reads[name] = (self._plan_sensor(data, members[0]) if kinds[name] == "sensor"
                                else ("sensordata", members[0]._index))

    def fits(self, core_name: str, cores: list[Any], readers: dict[str, list[Any]]) -> bool:
        """Whether this session steps these members (the same modules, cores on the same scenes)."""
        return (core_name == self.core_name and len(cores) == self.count
                and all(c is mine and c._compiled is s
                        for c, mine, s in zip(cores, self.cores, self.scenes, strict=True))
                and readers.keys() == self.readers.keys()
                and all(all(a is b for a, b in zip(readers[n], self.readers[n], strict=True)) for n in readers))

    def load(self) -> None:
        """Take each core's state (its MjData, whole state and stages) as the batch's, before a batch."""
        self.batch.set_models([s.model for s in self.scenes])  # (a parameter may have edited one)
        state = self.batch.state
        for k, s in enumerate(self.scenes):
            mujoco.mj_getState(s.model, s.data, state[k], _STATE)
        self.batch.forward(stage=_VEL)
        self.seen = self._diverged(None)
        # the derived fields read, as the cores' datas hold them now (the batch's are the stages the
        # forward call made, without the last step's acceleration stage) until the first step
        self.now: dict[str, np.ndarray] = {}
        self.stepped = False

    # -- plans: each copy as (MjData field, positions there, columns of the module's ports) ---------------
    def _plan_in(self, data: Any, core: Any, dst: Any, di: Any, src: Any, si: Any) -> tuple:
        field, where = _field(data, dst) or self._unplanned(dst)
        cols = _positions(src, core.inp_flat)
        if cols is None:
            raise RuntimeError(f"core {core.name!r}: an input copy reads outside its inputs")
        return (field, contiguous(where[_pick(di, len(where))]),
                contiguous(cols[_pick(si, len(cols)) if si is not None else slice(None)]))

    def _plan_out(self, data: Any, core: Any, dst: Any, di: Any, src: Any, si: Any) -> tuple:
        field, where = _field(data, src) or self._unplanned(src)
        cols = _positions(dst, core.out_flat)
        if cols is None:
            raise RuntimeError(f"core {core.name!r}: an output copy writes outside its outputs")
        return (field, contiguous(where[_pick(si, len(where)) if si is not None else slice(None)]),
                contiguous(cols[_pick(di, len(cols))]))

    def _plan_sensor(self, data: Any, sensor: Any) -> list[tuple]:
        plan = []
        for (port, _cut), (source, index) in zip(sensor._writes, sensor._sources, strict=True):
            field, where = _field(data, source) or self._unplanned(source)
            cols = _positions(port, sensor.out_flat)
            if cols is None:
                raise RuntimeError(f"sensor {sensor.name!r}: a port outside its outputs")
            plan.append((field, contiguous(where[index]), contiguous(cols.reshape(-1))))
        return plan

    def _unplanned(self, view: np.ndarray) -> tuple[str, np.ndarray]:
        raise RuntimeError(f"the core's data field of an array of shape {view.shape} is not one of {_FIELDS}")

    # -- the arrays --------------------------------------------------------------------------------------------
    def _array(self, field: str) -> np.ndarray:
        """Field ``field`` of every branch, ``(branches, size)``: the batch's (its state rows, or what it
        copied out after the last step), or before the first step the cores' own values."""
        got = self.now.get(field)
        if got is None:
            if self.stepped or field in _STATE_FIELDS:
                got = self.batch.bind(field).reshape(self.count, -1)
            else:
                got = np.stack([getattr(c._compiled.data, field).reshape(-1) for c in self.cores])
            self.now[field] = got
        return got

    def _diverged(self, rows: np.ndarray | None) -> np.ndarray:
        counts = self.batch.warning[:, _DIVERGED, 1].sum(axis=1)  # (a slice: the three are neighbours)
        return counts if rows is None else counts[rows]

    def _rows(self, name: str, members: Sequence[Any]) -> np.ndarray | None:
        """The batch rows of ``members`` (None: every branch, in order)."""
        if len(members) == self.count:
            return None
        of = self.rows[name]
        return np.fromiter((of[id(m)] for m in members), dtype=np.intp, count=len(members))

    # -- the steps ---------------------------------------------------------------------------------------------
    def handles(self, name: str) -> bool:
        return name in self.kinds

    def step_batch(self, name: str, members: Sequence[Any], t_ns: int, dt_ns: int, inp: np.ndarray,
                   out: np.ndarray, failed: dict[int, BaseException]) -> np.ndarray:
        kind = self.kinds[name]
        rows = self._rows(name, members)
        if kind == "core":
            return self._step_core(members, rows, inp, out, failed)
        if kind == "sensor":
            new = np.empty(out.shape)
            for field, where, cols in self.reads[name]:
                values = self._array(field)
                new[:, cols] = values[:, where] if rows is None else values[rows][:, where]
            return new
        values = self._array("sensordata")
        picked = values[:, self.reads[name][1]] if rows is None else values[rows][:, self.reads[name][1]]
        new = np.empty(out.shape)
        for k, member in enumerate(members):
            try:
                new[k] = member.support(picked[k].tolist())
            except Exception as exc:  # this branch's failure
                failed[k] = exc
        return new

    def _step_core(self, members: Sequence[Any], rows: np.ndarray | None, inp: np.ndarray, out: np.ndarray,
                   failed: dict[int, BaseException]) -> np.ndarray:
        every = rows is None
        if self.vel is not None:
            vel = np.isnan(inp[:, self.vel])
            if not vel.all():
                for k in np.flatnonzero(~vel.all(axis=1)):
                    failed[int(k)] = RuntimeError("a velocity input holds a value: the core steps alone")
        for field, where, cols in self.ins:
            target = self._array(field)
            if every:
                target[:, where] = inp[:, cols]
            else:
                target[(rows, where) if isinstance(where, slice) else np.ix_(rows, where)] = inp[:, cols]
        ids = None if every else rows
        if failed:  # (those asking for velocities do not step here)
            keep = np.array([k not in failed for k in range(len(members))])
            ids = (np.arange(self.count) if every else rows)[keep]
        try:
            self.batch.step(ids, nstep=self.nsub, stage=_VEL)
        except _mjbatch.SimulationError as exc:  # MuJoCo raised in some branches: they kept their state
            at = {r: k for k, r in enumerate(np.arange(self.count) if every else rows)}
            for r in exc.ids:
                failed[at[int(r)]] = RuntimeError(f"core {members[0].name!r}: MuJoCo raised: "
                                                  f"{self.batch.error(int(r))}")
        if not self.stepped:  # the derived fields are the batch's from now on
            self.stepped = True
            self.now = {f: a for f, a in self.now.items() if f in _STATE_FIELDS}
        now = self._diverged(rows)
        seen = self.seen if every else self.seen[rows]
        for k in () if np.array_equal(now, seen) else np.flatnonzero(now != seen):
            failed.setdefault(int(k), PhysicsDivergedError(members[int(k)].name, "step", None,
                                                           "MuJoCo counted a bad position, velocity or acceleration"))
        new = np.array(out)
        for field, where, cols in self.outs:
            values = self._array(field)
            new[:, cols] = values[:, where] if every else values[rows][:, where]
        return new

    # -- the end ---------------------------------------------------------------------------------------------
    def sync(self, rows: Sequence[int]) -> None:
        """Write the batch's simulation of each of ``rows`` back into its core's MjData (whole), before the
        branch's states are read."""
        for r in rows:
            s = self.cores[r]._compiled
            self.batch.get_data(int(r), s.data)

    def close(self) -> None:
        """Let the batch go (its threads and datas)."""
        self.batch = None  # type: ignore[assignment]

