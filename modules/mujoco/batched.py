"""The MuJoCo core's batched step (`MujocoCore.step_batch`): the cores of N branches of one world, stepped
once a tick together, their physics on threads.

Each core's tick is its own `MujocoCore.step`, cut in three: its inputs copied into its MjData (Python,
a few copies a core), the physics (`mj_step2`, the substeps' `mj_step`, `mj_step1`: MuJoCo's C, which
the bindings call with the GIL released), its outputs copied onto its row of the bus (Python). The
physics of all N cores runs in one go on ``workers`` threads (this thread takes a share too), each
stepping its slice of the cores one after the other: one hand-over per thread and tick, not per core.
The calls and their order on each core's data are those of `MujocoCore.step`, so a core's state is the
same bit for bit whichever thread stepped it and whatever the others did.

A core that needs Python between its physics calls steps alone, with its own `step`, before the rest:
an animated robot's (its motion is set between `mj_step2` and `mj_step1`) and one whose velocity input
holds a value. A core that diverges (MuJoCo counted a bad position, velocity or acceleration) goes into
``failed`` with the `PhysicsDivergedError` its own step raises; the others go on.
"""

from __future__ import annotations

import functools
import itertools
import os
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import mujoco

from dynabrain.orchestrator.kernel.errors import PhysicsDivergedError

_step1, _step2, _step = mujoco.mj_step1, mujoco.mj_step2, mujoco.mj_step
_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()
PROBE_TICKS, EVERY_TICKS = 8, 256
"""The physics of a tick goes on threads only where that is faster here: for each model and count of
branches, the first `PROBE_TICKS` ticks of every `EVERY_TICKS` are stepped on this thread alone, the next
`PROBE_TICKS` on threads, and the ticks after them the way whose best tick was shorter (a hand-over to
the threads and back costs tens to hundreds of microseconds a tick, more on a loaded machine: 8 swings
are faster on one thread, 64 humanoids on an idle machine's cores). Either way each core's steps are the
same calls, so the choice changes no result."""
_TIMES: dict[tuple[int, int], list[float]] = {}  # (id of a model, branches) -> [best alone, best threaded, ticks]


@functools.cache
def workers() -> int:
    """How many threads step the physics: every core of the machine (``DYNABRAIN_LOCKSTEP_THREADS``
    sets another count; read once)."""
    given = os.environ.get("DYNABRAIN_LOCKSTEP_THREADS", "").strip()
    return max(1, int(given)) if given.isdigit() else os.cpu_count() or 1


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max(1, workers() - 1), thread_name_prefix="dynabrain-physics")
        return _POOL


def _physics(jobs: Sequence[tuple[Any, Any, int]]) -> None:
    """The physics of a slice of the cores: each one's tick as `MujocoCore.step` makes it."""
    for m, d, extra in jobs:
        _step2(m, d)
        if extra:
            _step(m, d, extra)
        _step1(m, d)


def step_cores(members: Sequence[Any], t_ns: int, dt_ns: int, failed: dict[int, BaseException]) -> None:
    """Step the cores ``members`` (one per branch) one tick: see the module docstring."""
    jobs: list[tuple[Any, Any, int]] = []
    stepped: list[tuple[int, Any, Any]] = []  # (index, core, compiled scene) of those in ``jobs``
    for k, core in enumerate(members):
        s = core._compiled
        if s.anim is not None or core._vel.tobytes() != core._vel_unset:
            try:  # Python between the halves of its step: the core's own step, alone
                core.step(t_ns, dt_ns)
            except Exception as exc:  # this branch's failure
                failed[k] = exc
            continue
        write_inputs(core, s)
        jobs.append((s.model, s.data, core._nsub - 1))
        stepped.append((k, core, s))
    _run(jobs)
    for k, core, s in stepped:
        bad = s.bad_qpos.number + s.bad_qvel.number + s.bad_qacc.number
        if bad != s.warnings_seen:
            failed[k] = PhysicsDivergedError(core.name, "step", None, core._divergence(s, bad))
            continue
        for dst, di, src, si in core._moves[2]:  # the outputs that can change in a step
            dst[di] = src if si is None else src[si]


def _run(jobs: list[tuple[Any, Any, int]]) -> None:
    """Step ``jobs``: on this thread alone, or cut into one slice per thread, this thread stepping the
    last, whichever was faster (see `PROBE_TICKS`)."""
    threads = min(workers(), len(jobs))
    if threads <= 1:
        _physics(jobs)
        return
    key = (id(jobs[0][0]), len(jobs))
    times = _TIMES.get(key)
    if times is None:
        if len(_TIMES) >= 1024:
            _TIMES.clear()
        times = _TIMES[key] = [float("inf"), float("inf"), 0]
    tick = int(times[2]) % EVERY_TICKS
    times[2] += 1
    if tick == 0:
        times[0] = times[1] = float("inf")
    threaded = PROBE_TICKS <= tick < 2 * PROBE_TICKS if tick < 2 * PROBE_TICKS else times[1] < times[0]
    t0 = time.perf_counter()
    if threaded:
        _threaded(jobs, threads)
    else:
        _physics(jobs)
    if tick < 2 * PROBE_TICKS:
        seconds = time.perf_counter() - t0
        times[threaded] = min(times[threaded], seconds)


def _threaded(jobs: list[tuple[Any, Any, int]], threads: int) -> None:
    """The jobs shared by ``threads`` threads (this one too), each taking the next job not taken yet:
    a thread the machine holds back (another process on its core) delays the tick by the job it has,
    not by a fixed share of the jobs."""
    taken = itertools.count()  # next() on it is atomic (the GIL)
    pool = _pool()
    futures: list[Future[None]] = [pool.submit(_take, jobs, taken) for _ in range(threads - 1)]
    try:
        _take(jobs, taken)
    finally:
        for future in futures:
            future.result()


def _take(jobs: list[tuple[Any, Any, int]], taken: Any) -> None:
    count = len(jobs)
    for k in taken:
        if k >= count:
            return
        m, d, extra = jobs[k]
        _step2(m, d)
        if extra:
            _step(m, d, extra)
        _step1(m, d)


def write_inputs(core: Any, s: Any) -> None:
    """The core's inputs (joint forces, motor controls, wrenches) into the MuJoCo data of its compiled
    scene ``s``, as its own step writes them (its plan of copies made once per scene)."""
    moves = core._moves
    if moves is None or moves[0] is not s:
        moves = core._moves = (s, *core._plan_moves(s))
    for dst, di, src, si in moves[1]:
        dst[di] = src if si is None else src[si]
