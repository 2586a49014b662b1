"""One branch of a batch: a start state, per-branch parameter overrides, per-tick inputs, ticks to run
and the signals to record; and what came of it. Every backend runs a branch with `run_branch`, on a
world of its own, so a branch is the same computation wherever it runs.

A branch, written out on one world (what a test compares each backend against)::

    world.import_state(start)                 # or restore(snapshot) in the world it came from
    for name, value in params.items():
        world.set(name, value)                # run-time parameters, before the first tick
    recorded = world.run(ticks, inputs=inputs, record=record)
    final = world.export_state()
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import DynabrainError, ModuleError
from .world import World


@dataclass(frozen=True)
class BranchTask:
    """What one branch runs. ``start`` is the bytes of `World.export_state`; ``inputs`` maps an input
    port to its values, shape ``(ticks, *port shape)``; ``params`` maps a run-time parameter to its value."""

    index: int
    start: bytes
    ticks: int
    inputs: dict[str, np.ndarray] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)
    record: tuple[str, ...] = ()
    keep_state: bool = True


@dataclass(frozen=True)
class BranchStatus:
    """How a branch ended: ``ok``, or failed with ``reason`` at ``failed_tick`` (the world's tick the
    failure rolled back to; None when it failed before its first tick or its worker died). ``lost``: its
    worker died (a process killed or crashed, a Ray actor gone) while it ran, so how the branch itself
    would end is unknown; run again, it may end well (or kill its worker again: then it is its doing)."""

    ok: bool
    reason: str | None = None
    failed_tick: int | None = None
    ticks_done: int = 0
    lost: bool = False

    def __str__(self) -> str:
        return "ok" if self.ok else f"failed: {self.reason}"


@dataclass(frozen=True)
class BranchOutcome:
    """A branch's result: its recorded signals (rows of ticks not done are NaN), its final state
    (bytes, when asked for; after a failure, the state the failure rolled back to), its status."""

    index: int
    signals: dict[str, np.ndarray]
    state: bytes | None
    status: BranchStatus


def run_branch(world: World, task: BranchTask, *, at_start: bool = False) -> BranchOutcome:
    """Run ``task`` on ``world`` (which it leaves in the branch's final state). A module that raises, a
    physics that diverges or a start state the world refuses is a failed branch, not an exception.
    ``at_start``: the world is in ``task.start`` already (it ended the previous branch there), so the
    import is skipped."""
    try:
        if not at_start:
            world.import_state(task.start)
        for name, value in task.params.items():
            world.set(name, value)
        signals = world.run(task.ticks, inputs=task.inputs, record=task.record)
        status = BranchStatus(True, ticks_done=task.ticks)
    except ModuleError as err:
        signals = getattr(err, "recorded", None) or _empty(world, task)
        status = BranchStatus(False, str(err), err.tick, getattr(err, "ticks_done", 0))
    except DynabrainError as err:  # refused before it ran: a bad state or parameter for this branch
        return BranchOutcome(task.index, _empty(world, task), None, BranchStatus(False, str(err)))
    state = world.export_state() if task.keep_state else None
    return BranchOutcome(task.index, signals, state, status)


def _empty(world: World, task: BranchTask) -> dict[str, np.ndarray]:
    out = {}
    for name in task.record:
        try:
            shape = np.shape(world.get(name))
        except DynabrainError:
            shape = ()
        out[name] = np.full((task.ticks, *shape), np.nan)
    return out


class BranchRunner:
    """A world of its own that runs branches: what a worker process holds, and what a Ray actor is.
    ``build`` makes the world (`World.rebuild`: `load_world` of the batch's scenario)."""

    def __init__(self, build: Any):
        self.world: World = build()
        self.last: bytes | None = None
        """The state the world is in after the last branch (as exported), when it was kept."""

    def run(self, task: BranchTask) -> BranchOutcome:
        """Run a branch; one that starts where the last one ended (a vector env's copy, a plan going
        on) continues on the world as it is, without importing the state again."""
        at_start = self.last is not None and (task.start is self.last or task.start == self.last)
        self.last = None
        outcome = run_branch(self.world, task, at_start=at_start)
        self.last = outcome.state
        return outcome

    def close(self) -> None:
        self.world.close()
