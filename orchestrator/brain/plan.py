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
raises or whose physics diverges is a failed child too.

It is A* as the books have it:

- the goal is tested when a node is popped from the frontier (the cheapest ``g + weight * h`` there),
  not when it is generated, so the plan returned is the cheapest found whatever the order of the
  actions (with a heuristic that never overestimates, and ``weight`` 1, the cheapest there is);
- a closed set: two nodes with the same key are one state, and only the cheaper path to it is kept
  (a push and its reverse do not bring the search back to a state it has seen). The key is the
  user's ``key(outcome)``, by default `signature`: every recorded signal's value rounded to
  ``resolution``, with the parameters the action set;
- every child of a node is one branch of one batch, whatever the actions' lengths; when the batch
  steps more branches at once than a node has children, the children of the next nodes of the
  frontier join the batch (``nodes_per_batch``), and the goal is still tested on the cheapest first;
- a child whose worker died (a process killed, a Ray actor lost: `BranchStatus.lost`) is run again,
  up to ``retries`` times, not pruned; one that kills its worker every time is a failed child.

A search that exhausts its budget returns the first goal, in the frontier's order, among the nodes it
generated and did not pop (found, but not known to be the cheapest), or else ``found=False`` with the
best node found (lowest heuristic).
"""

from __future__ import annotations

import heapq
import itertools
import time
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..kernel import portable
from ..kernel.errors import DynabrainError
from ..kernel.observers import Imagined
from ..kernel.world import World
from .batch import Batch, BatchResult

RESOLUTION = 1e-6
"""The default key's grid: a recorded value is rounded to a multiple of this (1 um for a position in m)."""
RETRIES = 2
"""How many times a child whose worker died is run again before it counts as failed."""


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
    key: Hashable = None
    """This state in the closed set (None when the search keeps none)."""

    def path(self) -> list[Node]:
        """The nodes from the root to this one."""
        out, node = [], self
        while node is not None:
            out.append(node)
            node = node.parent
        return out[::-1]


@dataclass(frozen=True)
class Outcome:
    """What the user's cost, heuristic, failure, goal and key functions see of one child: the ``action``
    taken from ``parent``, the ``signals`` it recorded (``(ticks, *shape)``); ``outcome[name]`` is a
    signal's last value. (The key function also sees the start once: action and parent None.)"""

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
    """Children evaluated (branches simulated; a branch run again after its worker died counts once)."""
    batches: int = 0
    failed: list[tuple[str, str]] = field(default_factory=list)
    """(the path of actions, the reason) of each failed child."""
    wall_s: float = 0.0
    ticks: int = 0
    """Ticks simulated, every branch together."""
    duplicates: int = 0
    """Children dropped: the closed set had their state, reached at no higher cost."""
    retried: int = 0
    """Branches run again because their worker died."""

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


def signature(outcome: Outcome, resolution: float = RESOLUTION) -> Hashable:
    """The default key of the state an action reached: each recorded signal's last value (the inputs
    the actions drive too) rounded to a multiple of ``resolution``, and the parameters it set. Two
    states with the same signature are the same to the search."""
    parts: list[Any] = []
    for name, values in outcome.signals.items():
        grid = np.round(np.asarray(values[-1], dtype=np.float64) / resolution) + 0.0  # -0.0 is 0.0
        grid = np.where(np.isnan(grid), np.nan, grid)  # one NaN
        parts.append((name, grid.tobytes()))
    action = outcome.action
    parts.append(tuple((n, repr(v)) for n, v in sorted(action.params.items())) if action is not None else None)
    return tuple(parts)


def search(world: World, actions: Sequence[Action], *, record: Sequence[str], goal: Callable[[Outcome], bool],
           heuristic: Callable[[Outcome], float], cost: Callable[[Outcome], float] | None = None,
           failed: Callable[[Outcome], Any] | None = None, start: bytes | None = None, max_expansions: int = 200,
           max_depth: int = 8, weight: float = 1.0, batch: Batch | None = None, backend: str = "auto",
           key: Callable[[Outcome], Hashable] | None = None, closed: bool = True, resolution: float = RESOLUTION,
           nodes_per_batch: int | None = None, retries: int = RETRIES) -> Plan:
    """A* from ``start`` (default: the world's state now) over ``actions``; see the module docstring.

    ``weight`` scales the heuristic (1: A*; above 1: greedier, fewer expansions). ``batch``: a Batch to
    evaluate children with (its workers are kept); otherwise one is made with ``backend`` and closed.
    ``key``: a state's key in the closed set (default: `signature` at ``resolution``); ``closed=False``
    keeps no closed set (a tree search: every path is its own node). ``nodes_per_batch``: frontier
    nodes whose children share a batch (default: as many as fill the batch's `Batch.parallelism`,
    at least one). ``retries``: runs again of a child whose worker died. The world does not change.
    """
    actions = list(actions)
    _check(world, actions, record, max_expansions, max_depth)
    if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
        raise DynabrainError(f"plan: retries must be an integer >= 0, got {retries!r}")
    if nodes_per_batch is not None and (not isinstance(nodes_per_batch, int) or nodes_per_batch < 1):
        raise DynabrainError(f"plan: nodes_per_batch must be a positive integer, got {nodes_per_batch!r}")
    if not resolution > 0:
        raise DynabrainError(f"plan: resolution must be a positive number, got {resolution!r}")
    driven = sorted({name for a in actions for name in a.inputs})
    params = sorted({name for a in actions for name in a.params})
    for a in actions:
        if set(a.params) != set(params):
            raise DynabrainError(f"plan: action {a.name!r} sets {sorted(a.params) or 'no parameters'}; every action "
                                 f"must set the same run-time parameters ({', '.join(params)})")
    signals = list(dict.fromkeys([*record, *driven]))  # an input's value at a node: what its parent left
    keyer = None if not closed else key or (lambda o: signature(o, resolution))
    own = batch is None
    batch = batch or Batch(world, backend=backend)
    stats = PlanStats()
    t0 = time.perf_counter()
    try:
        children = _Children(batch, actions, driven, params, signals,
                             cost or (lambda o: o.action.ticks * world.dt_ns * 1e-9), heuristic, failed, retries,
                             stats)
        per_batch = nodes_per_batch or max(1, -(-batch.parallelism // len(actions)))
        astar = _AStar(children, goal, keyer, weight, max_expansions, max_depth, per_batch, stats)
        end, found = astar.run(_root(world, start, signals))
    finally:
        stats.wall_s = time.perf_counter() - t0
        if own:
            batch.close()
    return _plan(end, found, record, stats)


def _root(world: World, start: bytes | None, signals: list[str]) -> Node:
    """The start as a node: its state and every signal's value there."""
    if start is None:
        held = {name: np.asarray(world.get(name), dtype=np.float64) for name in signals}
        return Node(world.export_state(), 0.0, float("inf"), 0, signals={n: held[n][None] for n in signals})
    twin = world.fork()
    try:
        twin.import_state(start)
        held = {name: np.asarray(twin.get(name), dtype=np.float64) for name in signals}
    finally:
        twin.close()
    return Node(start, 0.0, float("inf"), 0, signals={n: held[n][None] for n in signals})


class _AStar:
    """The search loop: a frontier ordered by ``g + weight * h`` (first pushed first among equals), the
    closed set (key -> the cost it was expanded at) and the cheapest cost each key was reached at."""

    def __init__(self, children: _Children, goal: Callable[[Outcome], bool],
                 key: Callable[[Outcome], Hashable] | None, weight: float, max_expansions: int, max_depth: int,
                 per_batch: int, stats: PlanStats):
        self.children, self.goal, self.key, self.weight = children, goal, key, weight
        self.max_expansions, self.max_depth, self.per_batch, self.stats = max_expansions, max_depth, per_batch, stats
        self.frontier: list[tuple[float, int, Node]] = []
        self.order = itertools.count()
        self.closed: dict[Hashable, float] = {}
        self.reached: dict[Hashable, float] = {}

    def run(self, root: Node) -> tuple[Node, bool]:
        """(the goal node, True), or (the best node found, False)."""
        if self.key is not None:
            root.key = self.key(Outcome(None, None, root.signals))  # type: ignore[arg-type]
        self._push(root)
        best = root
        while True:
            nodes, goal_node = self._take()
            if goal_node is not None:
                return goal_node, True
            if not nodes:
                break
            self.stats.expanded += len(nodes)
            for child in self.children.of(nodes):
                if child.h < best.h:
                    best = child
                if self.key is not None:
                    child.key = self.key(Outcome(child.action, child.parent, child.signals))  # type: ignore[arg-type]
                    if self.reached.get(child.key, float("inf")) <= child.g:
                        self.stats.duplicates += 1
                        continue
                self._push(child)
        goal_node = self._goal_left()  # the budget ran out: a goal generated but not popped
        return (goal_node, True) if goal_node is not None else (best, False)

    def _push(self, node: Node) -> None:
        if node.key is not None:
            self.reached[node.key] = node.g
        heapq.heappush(self.frontier, (node.g + self.weight * node.h if node.parent else 0.0, next(self.order), node))

    def _stale(self, node: Node) -> bool:
        """A node whose state was reached more cheaply since it was pushed, or expanded already."""
        if node.key is None:
            return False
        return self.reached[node.key] < node.g or self.closed.get(node.key, float("inf")) <= node.g

    def _is_goal(self, node: Node) -> bool:
        """The goal test, on a popped node (the start is never a goal: a plan has an action)."""
        if node.parent is None or node.action is None:
            return False
        return bool(self.goal(Outcome(node.action, node.parent, node.signals)))

    def _take(self) -> tuple[list[Node], Node | None]:
        """The next nodes to expand (up to ``per_batch``, the cheapest first), or a goal popped before
        any: the goal is returned only when it is the cheapest node of the frontier."""
        taken: list[Node] = []
        while self.frontier and len(taken) < self.per_batch and self.stats.expanded + len(taken) < self.max_expansions:
            _, order, node = heapq.heappop(self.frontier)
            if self._stale(node):
                continue
            if self._is_goal(node):
                if not taken:
                    return [], node
                heapq.heappush(self.frontier, (node.g + self.weight * node.h, order, node))  # after those taken
                break
            if node.key is not None:
                self.closed[node.key] = node.g
            if node.depth < self.max_depth:
                taken.append(node)
        return taken, None

    def _goal_left(self) -> Node | None:
        while self.frontier:
            _, _, node = heapq.heappop(self.frontier)
            if not self._stale(node) and self._is_goal(node):
                return node
        return None


class _Children:
    """Evaluates the children of some nodes: every action from every node, one batch, whatever the
    actions' lengths; a branch whose worker died is run again."""

    def __init__(self, batch: Batch, actions: list[Action], driven: list[str], params: list[str],
                 signals: list[str], cost: Callable, heuristic: Callable, failed: Callable | None, retries: int,
                 stats: PlanStats):
        self.batch, self.actions, self.driven, self.params, self.signals = batch, actions, driven, params, signals
        self.cost, self.heuristic, self.failed, self.retries, self.stats = cost, heuristic, failed, retries, stats

    def of(self, nodes: list[Node]) -> list[Node]:
        """The children of ``nodes`` that did not fail (the failed ones go to the statistics)."""
        pairs = [(node, action) for node in nodes for action in self.actions]
        request = {"ticks": [a.ticks for _, a in pairs], "starts": [n.state for n, _ in pairs],
                   "inputs": {name: [self._inputs(n, a, name) for n, a in pairs] for name in self.driven},
                   "params": {p: [a.params[p] for _, a in pairs] for p in self.params}}
        outcomes = self._run(request, list(range(len(pairs))))
        self.stats.generated += len(pairs)
        out = []
        for (node, action), (result, b) in zip(pairs, outcomes, strict=True):
            child = self._child(node, action, result, b)
            if child is not None:
                out.append(child)
        return out

    def _inputs(self, node: Node, action: Action, name: str) -> np.ndarray:
        if name in action.inputs:
            return _per_tick(self.batch.world, name, action.inputs[name], action.ticks)
        last = node.signals[name][-1]  # held where the parent left it
        return np.broadcast_to(last, (action.ticks, *last.shape))

    def _run(self, request: dict[str, Any], which: list[int]) -> list[tuple[BatchResult, int]]:
        """(the batch result, the row) of each branch in ``which``: one batch, then again for the
        branches whose worker died, up to ``retries`` times."""
        found: dict[int, tuple[BatchResult, int]] = {}
        for attempt in range(self.retries + 1):
            result = self.batch.run(
                [request["ticks"][i] for i in which], starts=[request["starts"][i] for i in which],
                inputs={n: [v[i] for i in which] for n, v in request["inputs"].items()},
                params={n: [v[i] for i in which] for n, v in request["params"].items()}, record=self.signals)
            self.stats.batches += 1
            self.stats.ticks += sum(s.ticks_done for s in result.status)
            lost = []
            for row, i in enumerate(which):
                found[i] = (result, row)
                if result.status[row].lost and attempt < self.retries:
                    lost.append(i)
            if not lost:
                break
            self.stats.retried += len(lost)
            which = lost
        return [found[i] for i in range(len(request["ticks"]))]

    def _child(self, node: Node, action: Action, result: BatchResult, b: int) -> Node | None:
        status = result.status[b]
        if not status.ok:
            reason = status.reason or "failed"
            if status.lost:
                reason += f" (run {self.retries + 1} times, its worker died each time)"
            self.stats.failed.append((" > ".join([*_names(node), action.name]), reason))
            return None
        recorded = {name: result.branch(name, b) for name in self.signals}
        outcome = Outcome(action, node, recorded)
        verdict = self.failed(outcome) if self.failed is not None else False
        if verdict:
            why = verdict if isinstance(verdict, str) else "the failure predicate holds"
            self.stats.failed.append((" > ".join([*_names(node), action.name]), why))
            return None
        state = result.states[b]
        assert state is not None
        return Node(state, node.g + float(self.cost(outcome)), float(self.heuristic(outcome)), node.depth + 1,
                    action, node, recorded)


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
