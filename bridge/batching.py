"""The ``batch`` call: N futures of a served world in one call, run by a `Batch` kept alive between calls
(its workers start once), with the limits a server puts on a request from the network.

The reply is one BATCH frame (`frames.batch`): the recorded arrays as float64 values, then a JSON
description of them (their names, shapes and offsets), of each branch's status and of the snapshots
that keep the branches' final states. The served world is only read: its state, tick and history are
what they were, and the final states become snapshots of it that ``restore`` (or another batch's
``starts``) takes.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from dynabrain.orchestrator.brain import BACKENDS, Batch, BatchResult
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.history import WorldState
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario.limits import MAX_MAGNITUDE

from . import frames
from . import protocol as p
from .checks import ValueRefusedError, check_batch_params

MAX_REASON = 2000
"""A failed branch's reason is cut to this many characters in the reply."""


@dataclass(frozen=True)
class BatchSettings:
    """How a server runs ``batch`` calls (``dynabrain serve --batch-backend ...``)."""

    backend: str = "auto"
    """`Batch`'s backend: ``auto``, ``serial``, ``processes`` or ``ray`` (forks of the world always use ``serial``)."""
    workers: int | None = None
    """Worker processes or Ray actors (default: every core)."""
    max_ticks: int = 1_000_000
    """Most branches x ticks in one call."""

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise DynabrainError(f"batch backend {self.backend!r} is unknown; backends: {', '.join(BACKENDS)}")
        if self.workers is not None and (isinstance(self.workers, bool) or self.workers < 1):
            raise DynabrainError(f"batch workers must be a positive integer, got {self.workers!r}")
        if isinstance(self.max_ticks, bool) or self.max_ticks < 1:
            raise DynabrainError(f"the most branch-ticks of a batch call must be a positive integer, got "
                                 f"{self.max_ticks!r}")


@dataclass(frozen=True)
class KeptState:
    """A state the bridge keeps as `World.export_state` bytes (a batch branch's final state): a snapshot
    that ``restore`` imports."""

    data: bytes
    tick: int


Stored = WorldState | KeptState
"""What the bridge keeps under a snapshot id."""


class BatchCall:
    """The ``batch`` call of one served world: one `Batch`, made now (a backend the world cannot use is
    refused at once), whose workers start at the first call and serve every later one until `close`."""

    def __init__(self, world: World, settings: BatchSettings, *, max_snapshots: int):
        self.world, self.settings, self.max_snapshots = world, settings, max_snapshots
        self.batch = Batch(world, backend=settings.backend, workers=settings.workers)

    def describe(self) -> dict[str, Any]:
        s = self.settings
        return {"backend": self.batch.backend, "workers": s.workers, "max_ticks": s.max_ticks}

    def run(self, a: p.BatchArgs, *, snapshot: Callable[[int], Stored], keep: Callable[[Stored], tuple[int, list[int]]],
            instance: int) -> bytes:
        """Check ``a`` against the limits, run it, keep the final states when asked (``keep`` registers a
        snapshot and returns its id and the ids evicted) and return the BATCH frame."""
        branches = self._branches(a)
        names = list(dict.fromkeys(a.record))
        self._check_limits(a, branches, names)
        inputs = {name: _numbers(values, name) for name, values in a.inputs.items()}
        check_batch_params(self.world, dict(a.params))
        starts, start_ticks = self._starts(a, snapshot, branches)
        result = self.batch.run(a.ticks, branches=branches, starts=starts, inputs=inputs, params=dict(a.params),
                                record=names, keep_states=a.keep_states)
        kept, evicted = self._keep(result, start_ticks, keep) if a.keep_states else ([None] * branches, [])
        return self._frame(result, names, kept, evicted, instance)

    def close(self) -> None:
        """Stop the workers (a later call starts them again)."""
        self.batch.close()

    # -- the request ----------------------------------------------------------------------------------------
    def _branches(self, a: p.BatchArgs) -> int:
        if a.branches is not None:
            if isinstance(a.starts, list) and len(a.starts) != a.branches:
                raise p.ProtocolError(f"batch: {len(a.starts)} starts for {a.branches} branches")
            return a.branches
        if isinstance(a.starts, list):
            return len(a.starts)
        raise p.ProtocolError("batch: say how many branches (branches), or give one start snapshot per branch")

    def _check_limits(self, a: p.BatchArgs, branches: int, names: list[str]) -> None:
        work = branches * a.ticks
        if work > self.settings.max_ticks:
            raise p.ProtocolError(f"batch: {branches} branches x {a.ticks} ticks = {work} branch-ticks, over this "
                                  f"server's limit of {self.settings.max_ticks} per call (`dynabrain serve "
                                  "--batch-max-ticks`): split it into several calls")
        if a.keep_states and branches > self.max_snapshots:
            raise p.ProtocolError(f"batch: keep_states keeps one snapshot per branch, and this server keeps at most "
                                  f"{self.max_snapshots} snapshots; {branches} branches are too many")
        values = 0
        for name in names:
            try:
                values += int(np.prod(np.shape(self.world.get(name)), dtype=np.int64))
            except DynabrainError:
                continue  # Batch names the unknown signal, before anything runs
        values *= work
        if values > frames.MAX_VALUES:
            raise p.ProtocolError(f"batch: the recorded signals would be {values} values, over the {frames.MAX_VALUES} "
                                  "one reply carries: record fewer signals, branches or ticks")

    def _starts(self, a: p.BatchArgs, snapshot: Callable[[int], Stored],
                branches: int) -> tuple[bytes | WorldState | list[bytes | WorldState], list[int]]:
        """What `Batch` takes as starts, and each branch's start tick."""
        if a.starts is None:
            with self.world.lock():  # the state and its tick together, even while the world's loop runs
                tick = self.world.tick_count
                return self.world.export_state(), [tick] * branches
        if not isinstance(a.starts, list):
            one = snapshot(a.starts)
            return _start(one), [one.tick] * branches
        stored = [snapshot(sid) for sid in a.starts]
        return [_start(s) for s in stored], [s.tick for s in stored]

    # -- the reply ------------------------------------------------------------------------------------------
    def _keep(self, result: BatchResult, start_ticks: list[int],
              keep: Callable[[Stored], tuple[int, list[int]]]) -> tuple[list[dict[str, int] | None], list[int]]:
        kept: list[dict[str, int] | None] = []
        evicted: list[int] = []
        for b, (state, status) in enumerate(zip(result.states, result.status, strict=True)):
            if state is None:
                kept.append(None)
                continue
            tick = start_ticks[b] + status.ticks_done if status.ok else status.failed_tick
            if tick is None:  # a failed branch without the tick it rolled back to: nothing to continue from
                kept.append(None)
                continue
            sid, gone = keep(KeptState(state, tick))
            evicted += gone
            kept.append({"snapshot": sid, "tick": tick})
        return kept, evicted

    def _frame(self, result: BatchResult, names: list[str], kept: list[dict[str, int] | None], evicted: list[int],
               instance: int) -> bytes:
        signals, chunks, at = [], [], 0
        for name in names:
            arr = result.signals[name]
            signals.append({"name": name, "shape": list(arr.shape[2:]), "offset": at})
            chunks.append(arr.reshape(-1))
            at += arr.size
        meta = {
            "branches": len(result.status), "ticks": result.ticks, "backend": result.backend,
            "wall_s": result.wall_s, "size": at, "signals": signals,
            "status": [{"ok": s.ok, "reason": None if s.reason is None else s.reason[:MAX_REASON],
                        "failed_tick": s.failed_tick, "ticks_done": s.ticks_done} for s in result.status],
            "snapshots": kept, "evicted": evicted,
        }
        values = np.concatenate(chunks) if chunks else np.zeros(0)
        w = self.world
        return frames.batch(values, json.dumps(meta, separators=(",", ":")).encode(), source=instance,
                            seq=w.tick_count, stamp=w.time_ns)


def _start(stored: Stored) -> bytes | WorldState:
    return stored.data if isinstance(stored, KeptState) else stored


def _numbers(values: list[Any], name: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise DynabrainError(f"batch: inputs[{name!r}]: expected finite numbers in nested lists of one shape, "
                             f"got {str(values)[:80]}") from None
    if not np.isfinite(arr).all():
        raise ValueRefusedError(f"batch: inputs[{name!r}]: the values are not all finite")
    if arr.size and float(np.max(np.abs(arr))) > MAX_MAGNITUDE:
        raise ValueRefusedError(f"batch: inputs[{name!r}]: the values must be within ±{MAX_MAGNITUDE:g}")
    return arr
