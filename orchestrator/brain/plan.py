"""Planning by simulating: best-first (A*) search over world states, each node's children evaluated as
one batch of futures (after EusDyna's block-moving planner: the brain tries actions in its simulator
and keeps what works, finding dynamic motions a careful symbolic planner would not).

    actions = [Action("push left fast", 40, inputs={"mover.velocity": [-0.8, 0, 0]}), ...]
    plan = search(world, actions, record=["core.box.pos"],
                  heuristic=lambda o: abs(o["core.box.pos"][0] + 0.4),
                  goal=lambda o: abs(o["core.box.pos"][0] + 0.4) < 0.02,
                  failed=lambda o: o["core.box.pos"][2] < 0.0 and "the box fell")
    plan.actions, plan.trajectory["core.box.pos"], plan.stats
    plan.execute(world)          # the same inputs on the world: the same outcome, bit for bit

The user gives the actions (each a short program: input values for some ticks and parameters set at
its start, applied to a copy of the world), a step cost (default: the action's duration in seconds), a
heuristic (an estimate of the cost still to go), a failure predicate (a failed child costs infinity and
is not expanded; its reason goes to the statistics) and a goal test. Each of these functions gets an
`Outcome`: what the action recorded, its last values, the node it started from. A branch whose module
raises or whose physics diverges is a failed child too. A search that exhausts its budget returns
``found=False`` with the best node found (lowest heuristic).
"""

from __future__ import annotations

import heapq
import itertools
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..kernel import portable
from ..kernel.errors import DynabrainError
from ..kernel.observers import Imagined
from ..kernel.world import World
from .batch import Batch


@dataclass(frozen=True)
class Action:
    """A short motion program: for ``ticks`` ticks, each input port in ``inputs`` takes its value (one
    value for every tick, or an array of shape ``(ticks, *port)``); ``params`` are run-time parameters
    set at its start."""

    name: str
    ticks: int
    inputs: Mapping[str, Any] = field(default_factory=dict)
    params: Mapping[str, Any] = field(default_factory=dict)

    def __str__(self) -> str:
        return self.name


@dataclass(eq=False)
class Node:
    """A world state the search reached: by which action from which parent, at what cost."""

    state: bytes
    g: float
    h: float
    depth: int
    action: Action | None = None
    parent: Node | None = None
    signals: dict[str, np.ndarray] = field(default_factory=dict)
    """What the action that led here recorded, ``(ticks, *shape)`` per signal (the root: one row, the
    values at the start), so ``node.signals[name][-1]`` is a signal's value at this node."""

    def path(self) -> list[Node]:
        """The nodes from the root to this one."""
        out, node = [], self
        while node is not None:
            out.append(node)
            node = node.parent
        return out[::-1]


@dataclass(frozen=True)
class Outcome:
    """What the user's cost, heuristic, failure and goal functions see of one child: the ``action``
    taken from ``parent``, the ``signals`` it recorded (``(ticks, *shape)``); ``outcome[name]`` is a
    signal's last value."""

    action: Action
    parent: Node
    signals: dict[str, np.ndarray]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.signals[name][-1]


@dataclass
class PlanStats:
    expanded: int = 0
    """Nodes whose children were evaluated."""
    generated: int = 0
    """Children evaluated (branches simulated)."""
    batches: int = 0
    failed: list[tuple[str, str]] = field(default_factory=list)
    """(the path of actions, the reason) of each failed child."""
    wall_s: float = 0.0
    ticks: int = 0
    """Ticks simulated, every branch together."""

    @property
    def nodes_per_s(self) -> float:
        return self.generated / self.wall_s if self.wall_s > 0 else float("inf")


@dataclass
class Plan:
    """The result of a search: ``found``; the ``actions`` from the start to the goal (or to the best
    node found); the ``states`` after each (the start first); the predicted ``trajectory`` of every
    recorded signal over the whole plan, ``(ticks, *shape)``; its ``cost``; the statistics."""

    found: bool
    actions: list[Action]
    states: list[bytes]
    trajectory: dict[str, np.ndarray]
    cost: float
    stats: PlanStats
    node: Node

    def imagine(self, world: World, name: str, branch: int = 0) -> Imagined | None:
        """Keep this plan's predicted trajectory as a future ``world`` imagined (`World.imagine`: a logged
        run writes it to ``/imagined/<name>/<branch>/...``), from the tick of its start state. None when
        the plan has no action (nothing was predicted)."""
        if not self.actions or not self.trajectory:
            return None
        return world.imagine(name, portable.decode(self.states[0]).tick, self.trajectory, branch=branch)

    def execute(self, world: World) -> dict[str, np.ndarray]:
        """Run the plan's actions on ``world`` (from the plan's start state: import it first to compare
        with the prediction) and return what it recorded, shaped like ``trajectory``."""
        rows: dict[str, list[np.ndarray]] = {name: [] for name in self.trajectory}
        for action in self.actions:
            for name, value in action.params.items():
                world.set(name, value)
            inputs = {name: _per_tick(world, name, value, action.ticks) for name, value in action.inputs.items()}
            recorded = world.run(action.ticks, inputs=inputs, record=list(rows))
            for name in rows:
                rows[name].append(recorded[name])
        return {name: np.concatenate(parts) if parts else np.zeros((0,)) for name, parts in rows.items()}


def search(world: World, actions: Sequence[Action], *, record: Sequence[str], goal: Callable[[Outcome], bool],
           heuristic: Callable[[Outcome], float], cost: Callable[[Outcome], float] | None = None,
           failed: Callable[[Outcome], Any] | None = None, start: bytes | None = None, max_expansions: int = 200,
           max_depth: int = 8, weight: float = 1.0, batch: Batch | None = None, backend: str = "auto") -> Plan:
    """A* from ``start`` (default: the world's state now) over ``actions``; see the module docstring.

    ``weight`` scales the heuristic (1: A*; above 1: greedier, fewer expansions). ``batch``: a Batch to
    evaluate children with (its workers are kept); otherwise one is made with ``backend`` and closed.
    The world itself does not change.
    """
    actions = list(actions)
    _check(world, actions, record, max_expansions, max_depth)
    cost = cost or (lambda o: o.action.ticks * world.dt_ns * 1e-9)
    driven = sorted({name for a in actions for name in a.inputs})
    params = sorted({name for a in actions for name in a.params})
    for a in actions:
        if set(a.params) != set(params):
            raise DynabrainError(f"plan: action {a.name!r} sets {sorted(a.params) or 'no parameters'}; every action "
                                 f"must set the same run-time parameters ({', '.join(params)})")
    signals = list(dict.fromkeys([*record, *driven]))  # an input's value at a node: what its parent left
    own = batch is None
    batch = batch or Batch(world, backend=backend)
    stats = PlanStats()
    t0 = time.perf_counter()
    try:
        root_state = start if start is not None else world.export_state()
        held = {name: np.asarray(world.get(name), dtype=np.float64) for name in signals}
        if start is not None:  # the values in that state
            twin = world.fork()
            try:
                twin.import_state(start)
                held = {name: np.asarray(twin.get(name), dtype=np.float64) for name in signals}
            finally:
                twin.close()
        root = Node(root_state, 0.0, 0.0, 0, signals={n: held[n][None] for n in signals})
        order = itertools.count()
        frontier: list[tuple[float, int, Node]] = [(0.0, next(order), root)]
        best = root
        best.h = float("inf")
        goal_node: Node | None = None
        while frontier and stats.expanded < max_expansions:
            _, _, node = heapq.heappop(frontier)
            if node.depth >= max_depth:
                continue
            stats.expanded += 1
            for child, reason in _expand(batch, node, actions, driven, params, signals, cost, heuristic, failed,
                                         stats):
                if child is None:
                    stats.failed.append((" > ".join([*_names(node), reason[0]]), reason[1]))
                    continue
                if child.h < best.h:
                    best = child
                if goal(Outcome(child.action, node, child.signals)):  # type: ignore[arg-type]
                    goal_node = child
                    break
                heapq.heappush(frontier, (child.g + weight * child.h, next(order), child))
            if goal_node is not None:
                break
    finally:
        stats.wall_s = time.perf_counter() - t0
        if own:
            batch.close()
    end = goal_node or best
    return _plan(end, goal_node is not None, record, stats)


def _expand(batch: Batch, node: Node, actions: list[Action], driven: list[str], params: list[str],
            signals: list[str], cost: Callable, heuristic: Callable, failed: Callable | None, stats: PlanStats):
    """Evaluate every action from ``node`` (one batch per action length); yield (child, None) or
    (None, (action name, reason))."""
    by_ticks: dict[int, list[Action]] = {}
    for a in actions:
        by_ticks.setdefault(a.ticks, []).append(a)
    for ticks, group in by_ticks.items():
        inputs = {}
        for name in driven:
            last = node.signals[name][-1]
            inputs[name] = np.stack([_per_tick(batch.world, name, a.inputs[name], ticks) if name in a.inputs
                                     else np.broadcast_to(last, (ticks, *last.shape)) for a in group])
        result = batch.run(ticks, branches=len(group), starts=[node.state] * len(group), inputs=inputs,
                           params={p: [a.params[p] for a in group] for p in params}, record=signals)
        stats.batches += 1
        stats.generated += len(group)
        stats.ticks += sum(s.ticks_done for s in result.status)
        for b, action in enumerate(group):
            status = result.status[b]
            if not status.ok:
                yield None, (action.name, status.reason or "failed")
                continue
            recorded = {name: result.signals[name][b] for name in signals}
            outcome = Outcome(action, node, recorded)
            verdict = failed(outcome) if failed is not None else False
            if verdict:
                yield None, (action.name, verdict if isinstance(verdict, str) else "the failure predicate holds")
                continue
            step = float(cost(outcome))
            child = Node(result.states[b], node.g + step, float(heuristic(outcome)), node.depth + 1, action, node,
                         recorded)  # type: ignore[arg-type]
            yield child, None


def _plan(end: Node, found: bool, record: Sequence[str], stats: PlanStats) -> Plan:
    path = end.path()
    steps = path[1:]
    trajectory = {name: (np.concatenate([n.signals[name] for n in steps]) if steps else np.zeros((0,)))
                  for name in record}
    return Plan(found, [n.action for n in steps], [n.state for n in path], trajectory, end.g, stats, end)


def _names(node: Node) -> list[str]:
    return [n.action.name for n in node.path()[1:] if n.action is not None]


def _per_tick(world: World, name: str, value: Any, ticks: int) -> np.ndarray:
    shape = np.shape(world.get(name))
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape == shape:
        return np.broadcast_to(arr, (ticks, *shape))
    if arr.shape != (ticks, *shape):
        raise DynabrainError(f"plan: the value for {name} has shape {arr.shape}; it needs {shape} (every tick) or "
                             f"{(ticks, *shape)}")
    return arr


def _check(world: World, actions: list[Action], record: Sequence[str], max_expansions: int, max_depth: int) -> None:
    if not actions:
        raise DynabrainError("plan: give at least one action")
    if isinstance(record, str):
        raise DynabrainError("plan: record is a list of signal names")
    for name in record:
        world.get(name)  # an unknown signal: its error now
    for a in actions:
        if not isinstance(a, Action):
            raise DynabrainError(f"plan: {a!r} is not an Action")
        if isinstance(a.ticks, bool) or not isinstance(a.ticks, int) or a.ticks < 1:
            raise DynabrainError(f"plan: action {a.name!r} lasts {a.ticks!r} ticks; it needs a positive integer")
        for name, value in a.inputs.items():
            full = world.settable(name)
            if not isinstance(full, str):
                raise DynabrainError(f"plan: action {a.name!r}: {name!r} is a parameter; put it in params")
            try:
                _per_tick(world, name, value, a.ticks)
            except DynabrainError as exc:
                raise DynabrainError(f"plan: action {a.name!r}: {exc}") from None
        for name in a.params:
            target = world.settable(name)
            if isinstance(target, str):
                raise DynabrainError(f"plan: action {a.name!r}: {name!r} is an input port; put it in inputs")
    if max_expansions < 1 or max_depth < 1:
        raise DynabrainError("plan: max_expansions and max_depth must be positive")
