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
values for input ports, runs ``ticks`` ticks (one count for all, or one per branch) and records the
signals asked for. A branch is exactly `branch.run_branch` on a world of its own; its result is
bit-identical to the same inputs stepped alone on the world in-process, whatever the backend, and
whatever the other branches of its batch are.

Branches of different lengths share one batch (a planner's pushes and waits, a controller's horizons)::

    result = batch.run([40, 100, 250], starts=[s0, s1, s1],
                       inputs={"mover.velocity": [v40, v100, v250]})    # (ticks of each, *port)
    result.signals["box.pos"]              # (3, 250, 3): rows past a branch's ticks are NaN

``submit`` takes the same request and returns a future at once (a controller goes on stepping its
world; `concurrent.futures.Future.result` takes the batch later)::

    future = batch.submit(50, branches=8, inputs={("left.target", "right.target"): mirrored})
    ...                                    # one sequence broadcast to several ports
    result = future.result()

Backends, one API:

- ``serial``: in this process, on one private fork of the world (for debugging; any world);
- ``processes``: worker processes, each building a copy of the world with ``world.rebuild`` (set by
  `load_world`) or ``build=``; states cross as exported bytes; every core is used;
- ``threads``: a world whose only module is a MuJoCo core, through ``mujoco.rollout`` on threads
  (no Python per step; `modules.mujoco.rollout_backend` says what it maps and refuses);
- ``lockstep``: every branch in this process, advanced tick by tick together: the N physics of a tick
  in one call on threads (GIL released; by default MuJoCo's own batch, whose arrays the sensors and
  the ZMP read for every branch at once: `modules.mujoco.mjbatch`), each other module stepped once
  for all branches through its batched step (`Module.step_batch`: numpy in the servo; others branch
  by branch); any world, per-branch starts, parameters and inputs (`lockstep.LockstepBackend`);
  ``physics="threads"`` steps each branch's own MjData on threads, ``physics="mjwarp"`` on MJWarp
  (warp's CPU device, or a GPU: `modules.mujoco.warp_batch`);
- ``ray``: the same workers as Ray actors, on a local Ray or a cluster (``address=``), for a brain
  that outgrows one machine (``pip install 'dynabrain[ray]'``);
- ``auto``: on a machine with more than one core, ``processes`` when the world can be rebuilt (the
  fastest for a robot with its modules: ``bench/predict.py``), else ``lockstep`` (a world built in
  Python: its physics still on every core); ``serial`` on one core.

Nothing of the world changes during a batch: it is only read (its state exported) when a run starts
or is submitted. Every name, shape and count is checked before anything runs. Batches run one after
the other, in the order they were asked for: `run` waits for those submitted before it.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..kernel import portable
from ..kernel.branch import BranchOutcome, BranchRunner, BranchStatus, BranchTask
from ..kernel.errors import DynabrainError, WiringError
from ..kernel.history import WorldState
from ..kernel.observers import Imagined
from ..kernel.plugins import resolve_class
from ..kernel.world import World

THREADS_BACKEND = "dynabrain.modules.mujoco.rollout_backend:RolloutBackend"
"""The ``threads`` backend, by class path (resolved when asked: the brain imports no shipped module)."""
BACKENDS = ("auto", "serial", "processes", "ray", "threads", "lockstep")


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
    value after tick k+1 (NaN for ticks a failed branch did not run, and past the end of a branch shorter
    than the longest); ``states[b]`` is branch b's final state as `World.export_state` bytes (None when
    not kept or when its worker died); ``status[b]`` says whether it ran to the end. ``ticks`` is the
    longest branch's count, ``branch_ticks[b]`` branch b's."""

    signals: dict[str, np.ndarray]
    states: list[bytes | None]
    status: list[BranchStatus]
    ticks: int
    backend: str
    wall_s: float
    branch_ticks: list[int] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    """What the backend did other than the usual (``lockstep``: branches stepped in groups, or run alone)."""

    def branch(self, name: str, b: int) -> np.ndarray:
        """What branch ``b`` recorded of ``name``, its own ticks only: ``(branch_ticks[b], *shape)``."""
        return self.signals[name][b, :self.branch_ticks[b]] if self.branch_ticks else self.signals[name][b]

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
                 address: str | None = None, build: Callable[[], World] | None = None, physics: str | None = None):
        if backend not in BACKENDS:
            raise DynabrainError(f"batch backend {backend!r} is unknown; backends: {', '.join(BACKENDS)}")
        if physics is not None and backend != "lockstep":
            raise DynabrainError(f"batch: physics={physics!r} chooses how the lockstep backend steps its MuJoCo "
                                 f"cores; backend {backend!r} steps each world's own")
        if workers is not None and (not isinstance(workers, int) or workers < 1):
            raise DynabrainError(f"batch workers must be a positive integer, got {workers!r}")
        self.world = world
        self.build = build if build is not None else world.rebuild
        if backend == "auto":
            many = (os.cpu_count() or 1) > 1
            backend = ("processes" if self.build is not None else "lockstep") if many else "serial"
        if backend in ("processes", "ray") and self.build is None:
            raise DynabrainError(f"batch backend {backend!r} builds a copy of the world in each worker: make the "
                                 "world with load_world (it knows how), or pass build=<a picklable call>")
        self.backend, self.workers, self.address, self._physics = backend, workers, address, physics
        self._pool: Any = None
        self._scratch: BranchRunner | None = None
        self._issued: dict[int, bytes] = {}  # final states this batch returned: starts that need no check
        self._issued_lock = threading.Lock()  # written by the thread that runs submitted batches
        self._runner: ThreadPoolExecutor | None = None  # runs submitted batches, one after the other
        self._last: Future[BatchResult] | None = None  # the batch submitted last

    @property
    def parallelism(self) -> int:
        """How many branches this batch steps at once (1 on ``serial``): what a caller fills a batch to."""
        if self.backend == "serial":
            return 1
        if self._pool is not None and hasattr(self._pool, "size"):
            return int(self._pool.size)
        return self.workers or os.cpu_count() or 1

    # -- running -----------------------------------------------------------------------------------------
    def run(self, ticks: int | Sequence[int], *, branches: int | None = None,
            starts: bytes | WorldState | Sequence[bytes | WorldState] | None = None,
            inputs: Mapping[str | tuple[str, ...], Any] | None = None, params: Mapping[str, Any] | None = None,
            record: Sequence[str] = (), keep_states: bool = True) -> BatchResult:
        """Run ``branches`` futures for ``ticks`` ticks each and return what they recorded.

        ``ticks``: one count for every branch, or one per branch. ``starts``: None (the world now, for
        every branch), one state for all, or one per branch (`World.export_state` bytes or snapshots of
        the world). ``inputs``: input port (or a tuple of ports: the same values for each) -> values of
        shape ``(ticks, *port)`` for every branch, ``(branches, ticks, *port)``, or a list of one
        ``(ticks of that branch, *port)`` array per branch (with counts per branch, a branch takes the
        first rows of a longer array). ``params``: run-time parameter -> one value for every branch, or
        a sequence of one value per branch. ``record``: signals to return. The branch count comes from
        ``branches``, a per-branch ``ticks`` or a per-branch ``starts``. Waits for submitted batches.
        """
        tasks = self._tasks(ticks, branches, starts, inputs or {}, params or {}, tuple(record), keep_states)
        if self._last is not None:
            self._last.exception()  # in order: the batches submitted before this one first
        return self._map(tasks, tuple(record))

    def submit(self, ticks: int | Sequence[int], *, branches: int | None = None,
               starts: bytes | WorldState | Sequence[bytes | WorldState] | None = None,
               inputs: Mapping[str | tuple[str, ...], Any] | None = None, params: Mapping[str, Any] | None = None,
               record: Sequence[str] = (), keep_states: bool = True) -> Future[BatchResult]:
        """`run` without waiting: the request is checked and its start states read now (the world may
        go on stepping), and a future returned; a thread of this batch runs it after those submitted
        before it. ``future.result()`` is its `BatchResult`, or raises what `run` would have raised."""
        tasks = self._tasks(ticks, branches, starts, inputs or {}, params or {}, tuple(record), keep_states)
        self._prepare()  # what reads the world is made here, on the caller's thread
        if self._runner is None:
            self._runner = ThreadPoolExecutor(1, thread_name_prefix="dynabrain-batch")
        self._last = self._runner.submit(self._map, tasks, tuple(record))
        return self._last

    def _map(self, tasks: list[BranchTask], record: tuple[str, ...]) -> BatchResult:
        t0 = time.perf_counter()
        outcomes = self._backend().map(tasks) if self.backend != "serial" else [self._serial(t) for t in tasks]
        wall = time.perf_counter() - t0
        with self._issued_lock:
            if len(self._issued) > 4096:
                self._issued.clear()
            self._issued.update((id(o.state), o.state) for o in outcomes if o.state is not None)
        result = _assemble(outcomes, tasks, self._shapes(record), self.backend, wall)
        result.notes = list(getattr(self._pool, "notes", ()))
        return result

    def _prepare(self) -> None:
        """Make the private world or the workers before a batch runs on another thread (the serial
        backend's fork and the threads backend's scratch world are copies of the world, read now)."""
        if self.backend == "serial":
            if self._scratch is None:
                self._scratch = BranchRunner(lambda: self.world.fork(self.world.name))
            return
        pool = self._backend()
        if hasattr(pool, "prepare"):
            pool.prepare()

    def _serial(self, task: BranchTask) -> BranchOutcome:
        if self._scratch is None:
            self._scratch = BranchRunner(lambda: self.world.fork(self.world.name))
        return self._scratch.run(task)

    def _backend(self) -> Any:
        if self._pool is None:
            if self.backend == "processes":
                from .pool import ProcessPool

                self._pool = ProcessPool(self.build, self.workers or os.cpu_count() or 1)
            elif self.backend == "lockstep":  # every branch here, tick by tick together (brain/lockstep.py)
                from .lockstep import LockstepBackend

                self._pool = LockstepBackend(self.world, self.workers, self._physics)
            elif self.backend == "threads":  # a core-only MuJoCo world, through mujoco.rollout (on MuJoCo's side)
                RolloutBackend = resolve_class(THREADS_BACKEND, object)  # noqa: N806 (a class)

                self._pool = RolloutBackend(self.world, self.workers)
            else:
                from .ray_pool import RayPool

                self._pool = RayPool(self.build, self.workers, self.address)
        return self._pool

    # -- checking the request -------------------------------------------------------------------------------
    def _tasks(self, ticks: Any, branches: int | None, starts: Any, inputs: Mapping[Any, Any],
               params: Mapping[str, Any], record: tuple[str, ...], keep: bool) -> list[BranchTask]:
        per_branch = isinstance(starts, Sequence) and not isinstance(starts, (bytes, bytearray))
        counts = _tick_counts(ticks)
        if branches is None:
            if counts is not None:
                branches = len(counts)
            elif per_branch:
                branches = len(starts)
            else:
                raise DynabrainError("batch: say how many branches (branches=N), or give one start state or one tick "
                                     "count per branch")
        if isinstance(branches, bool) or not isinstance(branches, (int, np.integer)) or branches < 1:
            raise DynabrainError(f"batch: the branch count must be a positive integer, got {branches!r}")
        branches = int(branches)
        if per_branch and len(starts) != branches:
            raise DynabrainError(f"batch: {len(starts)} start states for {branches} branches")
        if counts is not None and len(counts) != branches:
            raise DynabrainError(f"batch: {len(counts)} tick counts for {branches} branches")
        lengths = counts if counts is not None else [int(ticks)] * branches
        if per_branch:
            seen: dict[int, bytes] = {}  # the same object given for many branches is checked once
            start_bytes = [seen.get(id(s)) or seen.setdefault(id(s), self._state_bytes(s, f"starts[{b}]"))
                           for b, s in enumerate(starts)]
        else:
            start_bytes = [self._state_bytes(starts, "starts")] * branches
        drives: dict[str, list[np.ndarray]] = {}
        for key, values in inputs.items():
            ports = key if isinstance(key, tuple) else (key,)
            if not ports:
                raise WiringError("batch: an empty tuple of ports in inputs=")
            for name in ports:
                if name in drives:
                    raise WiringError(f"batch: input {name!r} is given twice in inputs=")
                drives[name] = self._input_values(name, values, lengths, counts is not None)
        overrides = {name: self._param_values(name, values, branches) for name, values in params.items()}
        self._shapes(record)  # unknown signals: an error now
        return [BranchTask(b, start_bytes[b], lengths[b], {n: v[b] for n, v in drives.items()},
                           {n: v[b] for n, v in overrides.items()}, record, keep) for b in range(branches)]

    def _state_bytes(self, start: Any, what: str) -> bytes:
        if start is None:
            return self.world.export_state()
        if isinstance(start, WorldState):
            return self.world.export_state(start)
        with self._issued_lock:
            own = self._issued.get(id(start)) is start
        if own:  # one of this batch's own results
            return start
        if isinstance(start, (bytes, bytearray, memoryview)):
            try:
                self.world.check_state(bytes(start))
            except DynabrainError as exc:
                raise DynabrainError(f"batch: {what}: {exc}") from None
            return bytes(start)
        raise DynabrainError(f"batch: {what} is a {type(start).__name__}; a start state is export_state bytes or a "
                             "snapshot of the world")

    def _input_values(self, name: str, values: Any, lengths: list[int], ragged: bool) -> list[np.ndarray]:
        """One ``(ticks of the branch, *port)`` array per branch (views where they can be)."""
        full = self.world.settable(name)
        if not isinstance(full, str):
            raise WiringError(f"batch: {name!r} is a parameter; give it in params=, inputs are input ports")
        shape = np.shape(self.world.get(full))
        branches, longest = len(lengths), max(lengths)
        if isinstance(values, (list, tuple)) and len(values) == branches and all(
                np.ndim(v) == len(shape) + 1 for v in values):  # one array per branch
            arrays = [np.asarray(v, dtype=np.float64) for v in values]
            for b, (arr, ticks) in enumerate(zip(arrays, lengths, strict=True)):
                if arr.shape[1:] != shape or len(arr) < ticks or (not ragged and len(arr) != ticks):
                    raise WiringError(f"batch: the values for input {full} of branch {b} have shape {arr.shape}; a "
                                      f"port of shape {shape} over {ticks} ticks needs {(ticks, *shape)}")
            return [arr[:ticks] for arr, ticks in zip(arrays, lengths, strict=True)]
        arr = np.asarray(values, dtype=np.float64)
        fits = (arr.shape[1:] == shape and len(arr) >= longest) if ragged else arr.shape == (longest, *shape)
        if fits:
            return [arr[:ticks] for ticks in lengths]
        fits = (arr.shape[0] == branches and arr.shape[2:] == shape and arr.shape[1] >= longest) if ragged and \
            arr.ndim == len(shape) + 2 else arr.shape == (branches, longest, *shape)
        if not fits:
            per = f"{longest} ticks" if not ragged else f"up to {longest} ticks"
            raise WiringError(f"batch: the values for input {full} have shape {arr.shape}; a port of shape {shape} "
                              f"over {per} needs {(longest, *shape)}, {(branches, longest, *shape)} or a list of "
                              "one (ticks, *port) array per branch")
        return [arr[b, :ticks] for b, ticks in enumerate(lengths)]

    def _param_values(self, name: str, values: Any, branches: int) -> list[Any]:
        if self.world.material_target(name) is not None:  # a body's own friction, restitution or mass
            items = list(values) if isinstance(values, (list, tuple, np.ndarray)) else [values] * branches
            if len(items) != branches:
                raise DynabrainError(f"batch: {len(items)} values of {name} for {branches} branches")
            for b, value in enumerate(items):
                mass = name.endswith(".mass")
                if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float, np.number))
                                          or not 0 <= float(value) < float("inf") or (mass and not value > 0)):
                    raise DynabrainError(f"batch: params[{name!r}][{b}] is {value!r}; a body's "
                                         + ("mass is a finite number above 0" if mass else
                                            "friction or restitution is a finite number >= 0")
                                         + ", or None for the core's")
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
        """Stop the workers (or the private world of ``serial``), after the submitted batches end."""
        if self._runner is not None:
            self._runner.shutdown(wait=True)
            self._runner, self._last = None, None
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


def _tick_counts(ticks: Any) -> list[int] | None:
    """One tick count per branch when ``ticks`` is a sequence, None when it is one count for all;
    either checked (positive integers)."""
    many = isinstance(ticks, (list, tuple, range, np.ndarray)) and np.ndim(ticks) == 1
    for t in ticks if many else [ticks]:
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t < 1:
            raise DynabrainError(f"batch: ticks must be a positive integer (or one per branch), got {t!r}")
    if many and not len(ticks):
        raise DynabrainError("batch: an empty list of tick counts")
    return [int(t) for t in ticks] if many else None


def _assemble(outcomes: Sequence[BranchOutcome], tasks: Sequence[BranchTask], shapes: dict[str, tuple[int, ...]],
              backend: str, wall: float) -> BatchResult:
    lengths = [t.ticks for t in tasks]
    longest = max(lengths)
    signals = {name: np.full((len(tasks), longest, *shape), np.nan) for name, shape in shapes.items()}
    for b, outcome in enumerate(outcomes):
        for name, values in outcome.signals.items():
            signals[name][b, :len(values)] = values
    return BatchResult(signals, [o.state for o in outcomes], [o.status for o in outcomes], longest, backend, wall,
                       lengths)
