"""A batch of imagined futures: N branches of one world, stepped together.

    with Batch(world, backend="processes") as batch:
        result = batch.run(500, branches=32, inputs={"servo.target": targets},   # (32, 500, 23)
                           params={"core.friction": np.linspace(0.3, 1.2, 32)},
                           record=["core.pelvis.pos", "zmp.zmp"])
    result.signals["core.pelvis.pos"]      # (32, 500, 3): after each tick
    result.status[7]                       # ok, or failed with its reason
    world.import_state(result.states[best])  # continue from the best future

Each branch starts from a state (the world's now, or one per branch: `World.export_state` bytes or
snapshots of the world), takes its own parameter overrides (set before its first tick) and per-tick
values for input ports, runs ``ticks`` ticks and records the signals asked for. A branch is exactly
`branch.run_branch` on a world of its own; its result is bit-identical to the same inputs stepped
alone on the world in-process, whatever the backend.

Backends, one API:

- ``serial``: in this process, on one private fork of the world (for debugging; any world);
- ``processes``: worker processes, each building a copy of the world with ``world.rebuild`` (set by
  `load_world`) or ``build=``; states cross as exported bytes; every core is used;
- ``threads``: a world whose only module is a MuJoCo core, through ``mujoco.rollout`` on threads
  (no Python per step; `rollout.RolloutBackend` says what it maps and refuses);
- ``ray``: the same workers as Ray actors, on a local Ray or a cluster (``address=``), for a brain
  that outgrows one machine (``pip install 'dynabrain[ray]'``);
- ``auto``: ``processes`` when the machine has more than one core and the world can be rebuilt,
  else ``serial``.

Nothing of the world changes during a batch: it is only read (its state exported) when a run starts.
Every name, shape and count is checked before anything runs.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..kernel import portable
from ..kernel.errors import DynabrainError, WiringError
from ..kernel.history import WorldState
from ..kernel.observers import Imagined
from ..kernel.world import World
from .branch import BranchOutcome, BranchRunner, BranchStatus, BranchTask

BACKENDS = ("auto", "serial", "processes", "ray", "threads")


class BranchStatuses:
    """``ok`` and ``failed`` of a batch's ``status`` list (one `BranchStatus` a branch): of a `BatchResult`
    here, and of the reply a brain gets over the bridge."""

    status: list[BranchStatus]

    @property
    def ok(self) -> bool:
        """Every branch ran to its end."""
        return all(s.ok for s in self.status)

    @property
    def failed(self) -> list[int]:
        return [b for b, s in enumerate(self.status) if not s.ok]


@dataclass
class BatchResult(BranchStatuses):
    """What a batch returns. ``signals[name]`` has shape ``(branches, ticks, *signal shape)``, row k the
    value after tick k+1 (NaN for ticks a failed branch did not run); ``states[b]`` is branch b's final
    state as `World.export_state` bytes (None when not kept or when its worker died); ``status[b]`` says
    whether it ran to the end."""

    signals: dict[str, np.ndarray]
    states: list[bytes | None]
    status: list[BranchStatus]
    ticks: int
    backend: str
    wall_s: float

    @property
    def ticks_per_s(self) -> float:
        """Ticks stepped per second of wall time, all branches together."""
        done = sum(s.ticks_done for s in self.status)
        return done / self.wall_s if self.wall_s > 0 else float("inf")

    def imagine(self, world: World, name: str, branches: int | Sequence[int] | None = None,
                start_tick: int | None = None) -> list[Imagined]:
        """Keep branches of this batch as futures ``world`` imagined (`World.imagine`: a logged run writes
        each to ``/imagined/<name>/<branch>/...``): ``branches`` (default: all), each with the ticks it
        ran. A branch starts at ``start_tick``, or else at its final state's tick less the ticks it ran,
        or else (no state kept) at the world's tick now."""
        chosen = range(len(self.status)) if branches is None else [branches] if isinstance(
            branches, (int, np.integer)) else list(branches)
        kept = []
        for b in chosen:
            if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not 0 <= b < len(self.status):
                raise DynabrainError(f"imagine: there is no branch {b!r} (the batch has {len(self.status)})")
            done, state = self.status[b].ticks_done, self.states[b]
            if done == 0 or not self.signals:
                continue
            start = start_tick if start_tick is not None else (
                portable.decode(state).tick - done if state is not None else world.tick_count)
            kept.append(world.imagine(name, start, {n: v[b, :done] for n, v in self.signals.items()}, branch=int(b)))
        return kept


class Batch:
    """N futures of ``world``, stepped together on ``backend`` (see the module docstring).

    ``workers``: how many processes or actors (default: every core, or Ray's CPUs); ``address``: the Ray
    cluster (``ray://host:10001`` or ``host:6379``; None starts or joins a local Ray); ``build``: a
    picklable call that builds the same world, for a world not made by `load_world`. Workers start at
    the first `run` and serve every later run until `close`.
    """

    def __init__(self, world: World, *, backend: str = "auto", workers: int | None = None,
                 address: str | None = None, build: Callable[[], World] | None = None):
        if backend not in BACKENDS:
            raise DynabrainError(f"batch backend {backend!r} is unknown; backends: {', '.join(BACKENDS)}")
        if workers is not None and (not isinstance(workers, int) or workers < 1):
            raise DynabrainError(f"batch workers must be a positive integer, got {workers!r}")
        self.world = world
        self.build = build if build is not None else world.rebuild
        if backend == "auto":
            backend = "processes" if (os.cpu_count() or 1) > 1 and self.build is not None else "serial"
        if backend in ("processes", "ray") and self.build is None:
            raise DynabrainError(f"batch backend {backend!r} builds a copy of the world in each worker: make the "
                                 "world with load_world (it knows how), or pass build=<a picklable call>")
        self.backend, self.workers, self.address = backend, workers, address
        self._pool: Any = None
        self._scratch: BranchRunner | None = None
        self._issued: dict[int, bytes] = {}  # final states this batch returned: starts that need no check

    # -- running -----------------------------------------------------------------------------------------
    def run(self, ticks: int, *, branches: int | None = None,
            starts: bytes | WorldState | Sequence[bytes | WorldState] | None = None,
            inputs: Mapping[str, Any] | None = None, params: Mapping[str, Any] | None = None,
            record: Sequence[str] = (), keep_states: bool = True) -> BatchResult:
        """Run ``branches`` futures for ``ticks`` ticks each and return what they recorded.

        ``starts``: None (the world now, for every branch), one state for all, or one per branch
        (`World.export_state` bytes or snapshots of the world). ``inputs``: input port -> values of
        shape ``(ticks, *port)`` for every branch or ``(branches, ticks, *port)``. ``params``: run-time
        parameter -> one value for every branch, or a sequence of one value per branch. ``record``:
        signals to return. The branch count comes from ``branches`` or from a per-branch ``starts``.
        """
        tasks = self._tasks(ticks, branches, starts, inputs or {}, params or {}, tuple(record), keep_states)
        t0 = time.perf_counter()
        outcomes = self._backend().map(tasks) if self.backend != "serial" else [self._serial(t) for t in tasks]
        wall = time.perf_counter() - t0
        if len(self._issued) > 4096:
            self._issued.clear()
        self._issued.update((id(o.state), o.state) for o in outcomes if o.state is not None)
        return _assemble(outcomes, tasks, self._shapes(record), ticks, self.backend, wall)

    def _serial(self, task: BranchTask) -> BranchOutcome:
        if self._scratch is None:
            self._scratch = BranchRunner(lambda: self.world.fork(self.world.name))
        return self._scratch.run(task)

    def _backend(self) -> Any:
        if self._pool is None:
            if self.backend == "processes":
                from .pool import ProcessPool

                self._pool = ProcessPool(self.build, self.workers or os.cpu_count() or 1)
            elif self.backend == "threads":  # a core-only MuJoCo world, through mujoco.rollout (brain/rollout.py)
                from .rollout import RolloutBackend

                self._pool = RolloutBackend(self.world, self.workers)
            else:
                from .ray_pool import RayPool

                self._pool = RayPool(self.build, self.workers, self.address)
        return self._pool

    # -- checking the request -------------------------------------------------------------------------------
    def _tasks(self, ticks: int, branches: int | None, starts: Any, inputs: Mapping[str, Any],
               params: Mapping[str, Any], record: tuple[str, ...], keep: bool) -> list[BranchTask]:
        if isinstance(ticks, bool) or not isinstance(ticks, (int, np.integer)) or ticks < 1:
            raise DynabrainError(f"batch: ticks must be a positive integer, got {ticks!r}")
        ticks = int(ticks)
        per_branch = isinstance(starts, Sequence) and not isinstance(starts, (bytes, bytearray))
        if branches is None:
            if not per_branch:
                raise DynabrainError("batch: say how many branches (branches=N), or give one start state per branch")
            branches = len(starts)
        if isinstance(branches, bool) or not isinstance(branches, (int, np.integer)) or branches < 1:
            raise DynabrainError(f"batch: the branch count must be a positive integer, got {branches!r}")
        branches = int(branches)
        if per_branch and len(starts) != branches:
            raise DynabrainError(f"batch: {len(starts)} start states for {branches} branches")
        if per_branch:
            seen: dict[int, bytes] = {}  # the same object given for many branches is checked once
            start_bytes = [seen.get(id(s)) or seen.setdefault(id(s), self._state_bytes(s, f"starts[{b}]"))
                           for b, s in enumerate(starts)]
        else:
            start_bytes = [self._state_bytes(starts, "starts")] * branches
        drives = {name: self._input_values(name, values, branches, ticks) for name, values in inputs.items()}
        overrides = {name: self._param_values(name, values, branches) for name, values in params.items()}
        self._shapes(record)  # unknown signals: an error now
        return [BranchTask(b, start_bytes[b], ticks, {n: v[b] for n, v in drives.items()},
                           {n: v[b] for n, v in overrides.items()}, record, keep) for b in range(branches)]

    def _state_bytes(self, start: Any, what: str) -> bytes:
        if start is None:
            return self.world.export_state()
        if isinstance(start, WorldState):
            return self.world.export_state(start)
        if self._issued.get(id(start)) is start:  # one of this batch's own results
            return start
        if isinstance(start, (bytes, bytearray, memoryview)):
            try:
                self.world.check_state(bytes(start))
            except DynabrainError as exc:
                raise DynabrainError(f"batch: {what}: {exc}") from None
            return bytes(start)
        raise DynabrainError(f"batch: {what} is a {type(start).__name__}; a start state is export_state bytes or a "
                             "snapshot of the world")

    def _input_values(self, name: str, values: Any, branches: int, ticks: int) -> np.ndarray:
        full = self.world.settable(name)
        if not isinstance(full, str):
            raise WiringError(f"batch: {name!r} is a parameter; give it in params=, inputs are input ports")
        shape = np.shape(self.world.get(full))
        arr = np.asarray(values, dtype=np.float64)
        if arr.shape == (ticks, *shape):
            return np.broadcast_to(arr, (branches, ticks, *shape))
        if arr.shape != (branches, ticks, *shape):
            raise WiringError(f"batch: the values for input {full} have shape {arr.shape}; a port of shape {shape} "
                              f"over {ticks} ticks needs {(ticks, *shape)} or {(branches, ticks, *shape)}")
        return arr

    def _param_values(self, name: str, values: Any, branches: int) -> list[Any]:
        if self.world.material_target(name) is not None:  # a body's own friction or restitution
            items = list(values) if isinstance(values, (list, tuple, np.ndarray)) else [values] * branches
            if len(items) != branches:
                raise DynabrainError(f"batch: {len(items)} values of {name} for {branches} branches")
            for b, value in enumerate(items):
                if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float, np.number))
                                          or not 0 <= float(value) < float("inf")):
                    raise DynabrainError(f"batch: params[{name!r}][{b}] is {value!r}; a body's friction or "
                                         "restitution is a finite number >= 0, or None for the core's")
            return items
        target = self.world.settable(name)
        if isinstance(target, str):
            raise WiringError(f"batch: {name!r} is an input port; give its per-tick values in inputs=")
        module, key = target
        spec = module.param_specs()[key]
        if not spec.runtime:
            raise DynabrainError(f"batch: parameter {name} cannot be changed at run time")
        vector = isinstance(spec.default, (list, tuple, np.ndarray))
        per_branch = isinstance(values, (list, tuple, np.ndarray)) and (
            not vector or np.ndim(np.asarray(values, dtype=object)) > np.ndim(np.asarray(spec.default, dtype=object)))
        items = list(values) if per_branch else [values] * branches
        if len(items) != branches:
            raise DynabrainError(f"batch: {len(items)} values of {name} for {branches} branches")
        for b, value in enumerate(items):
            try:
                spec.convert(value)
            except DynabrainError as exc:
                raise DynabrainError(f"batch: params[{name!r}][{b}]: {exc}") from None
        return items

    def _shapes(self, record: Sequence[str]) -> dict[str, tuple[int, ...]]:
        if isinstance(record, str):
            raise DynabrainError("batch: record is a list of signal names")
        return {name: self.world.signal_shape(name) for name in record}

    # -- closing ----------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the workers (or the private world of ``serial``)."""
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        if self._scratch is not None:
            self._scratch.close()
            self._scratch = None

    def __enter__(self) -> Batch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _assemble(outcomes: Sequence[BranchOutcome], tasks: Sequence[BranchTask], shapes: dict[str, tuple[int, ...]],
              ticks: int, backend: str, wall: float) -> BatchResult:
    signals = {name: np.full((len(tasks), ticks, *shape), np.nan) for name, shape in shapes.items()}
    for b, outcome in enumerate(outcomes):
        for name, values in outcome.signals.items():
            signals[name][b] = values
    return BatchResult(signals, [o.state for o in outcomes], [o.status for o in outcomes], ticks, backend, wall)
