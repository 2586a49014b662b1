"""The world's structure: modules present, connections, the bus layout and the schedule.

A `Structure` is immutable. Every edit (add or remove a module, connect, disconnect) builds a new
one, checked before it replaces the old; history keeps references to the structures it saw, which
is how a rollback restores the modules present as well as their states.

The bus is one flat float64 buffer; every port is a view into it. Saving the bus is one copy.

The schedule (the master algorithm, Gauss-Seidel): at each tick,
1. *delayed* connections copy their source values, as they are at the start of the tick;
2. modules due at this tick step in data-flow order; before each steps, its *direct* inputs are
   copied from their sources, which have already stepped this tick.
A connection is delayed when written so (``delay: true``) or when its source module is not
feedthrough (its outputs come from its state: a physics core). Direct connections must form no
cycle; a cycle is an algebraic loop and is reported with its path, unless its modules are declared a
loop to ``iterate`` (`orchestrator.kernel.iterate`: the loop is one entry of the schedule, its macro
step repeated from the saved states until its values agree). The world runs the schedule as one
generated function per structure (`Structure.compiled`, see `orchestrator.kernel.compiled`), or, when
made with ``compiled=False``, as a plain loop over the same entries (`Structure.plain`).
"""

from __future__ import annotations

import dataclasses
import functools
import heapq
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .compiled import CompiledTick, PlainTick
from .errors import AlgebraicLoopError, WiringError
from .finite import OutputCheck
from .iterate import LoopRunner, LoopSpec, check_loops, plan_loop
from .module import NO_PORTS, Module, Port, PortBinding
from .suggest import did_you_mean
from .units import same_unit


@dataclass(frozen=True)
class ModuleRecord:
    """A module as present in a world: its period in ticks and the tick phase it steps on."""

    name: str
    module: Module
    period_ticks: int
    phase: int
    period_ns: int
    inputs: tuple[Port, ...]
    outputs: tuple[Port, ...]


@dataclass(frozen=True)
class Connection:
    """``src`` (an output, ``module.port``) drives ``dst`` (an input)."""

    src: str
    dst: str
    delay: bool = False
    line: int | None = None

    def __str__(self) -> str:
        return f"{self.src} -> {self.dst}" + (" (delayed)" if self.delay else "")


def split_signal(name: str) -> tuple[str, str]:
    """``"core.aa.pos"`` -> ``("core", "aa.pos")``."""
    module, sep, port = name.partition(".")
    if not sep or not module or not port:
        raise WiringError(f"{name!r} is not a signal name of the form module.port")
    return module, port


@dataclass(frozen=True)
class Slot:
    """Where a port lives in the bus buffer."""

    start: int
    size: int
    shape: tuple[int, ...]
    port: Port
    direction: str  # "in" or "out"


class ModuleSlots(NamedTuple):
    """Where one module's ports lie on the bus, worked out once per layout (`BusLayout.modules`) so
    that binding a module to a bus (`binding`) is only making views."""

    inputs: tuple[tuple[str, int, int, tuple[int, ...] | None], ...]
    """(port name, first value, end, shape or None when the port is one-dimensional) of each input."""
    outputs: tuple[tuple[str, int, int, tuple[int, ...] | None], ...]
    """The same for each output."""
    inputs_flat: slice | None
    """The run of the bus holding the module's own inputs (not the ``view_of`` ones), or None."""
    outputs_flat: slice | None
    """The same for its own outputs."""

    def binding(self, buf: np.ndarray, read_only: np.ndarray,
                param_changed: Callable[[Module], None] | None = None) -> PortBinding:
        """The module's views on the bus ``buf``: inputs from ``read_only`` (a read-only view of it,
        so they are read-only), outputs writable."""
        inp = {n: read_only[a:b] if s is None else read_only[a:b].reshape(s) for n, a, b, s in self.inputs}
        out = {n: buf[a:b] if s is None else buf[a:b].reshape(s) for n, a, b, s in self.outputs}
        return PortBinding(inp, out, NO_PORTS if self.inputs_flat is None else read_only[self.inputs_flat],
                           NO_PORTS if self.outputs_flat is None else buf[self.outputs_flat], param_changed)


class BusLayout:
    """Offsets of every port of every module in one flat buffer."""

    def __init__(self, records: Sequence[ModuleRecord]):
        self.slots: dict[str, Slot] = {}
        offset = 0
        for rec in records:
            for direction, ports in (("in", rec.inputs), ("out", rec.outputs)):
                for port in ports:
                    if port.view_of is None:
                        self.slots[f"{rec.name}.{port.name}"] = Slot(offset, port.size, port.shape, port,
                                                                   direction)
                        offset += port.size
        for rec in records:
            for direction, ports in (("in", rec.inputs), ("out", rec.outputs)):
                for port in ports:
                    if port.view_of is not None:
                        self.slots[f"{rec.name}.{port.name}"] = self._view_slot(rec, port, direction)
        self.size = offset
        self.modules: dict[str, ModuleSlots] = {rec.name: self._module_slots(rec) for rec in records}
        """Module name -> where its ports lie (what binding it needs)."""
        values, given = np.zeros(offset), np.zeros(offset, dtype=bool)
        for slot in self.slots.values():  # blocks first, then the views into them (a view's start wins)
            if slot.port.start is not None:
                values[slot.start:slot.start + slot.size] = np.broadcast_to(
                    np.asarray(slot.port.start, dtype=np.float64), slot.shape).reshape(-1)
                given[slot.start:slot.start + slot.size] = True
        self.start_index = np.flatnonzero(given)
        """The bus positions whose ports have a start value (`Port.start`; the others start at 0) ..."""
        self.start_values = values[self.start_index]
        """... and those values."""

    def new_bus(self) -> np.ndarray:
        """A bus for this layout: every value at its port's start value, 0 where a port has none."""
        buf = np.zeros(self.size)
        if len(self.start_index):
            buf[self.start_index] = self.start_values
        return buf

    def _module_slots(self, rec: ModuleRecord) -> ModuleSlots:
        parts: list = []
        for ports in (rec.inputs, rec.outputs):
            slots = [(port, self.slots[f"{rec.name}.{port.name}"]) for port in ports]
            parts.append(tuple((p.name, s.start, s.start + s.size, None if s.shape == (s.size,) else s.shape)
                               for p, s in slots))
            own = [s for p, s in slots if p.view_of is None]
            parts.append(slice(own[0].start, own[-1].start + own[-1].size) if own else None)
        return ModuleSlots(parts[0], parts[2], parts[1], parts[3])

    def _view_slot(self, rec: ModuleRecord, port: Port, direction: str) -> Slot:
        base_name, index = port.view_of  # type: ignore[misc]
        base = self.slots.get(f"{rec.name}.{base_name}")
        if base is None or base.port.view_of is not None:
            raise WiringError(f"module {rec.name!r}: port {port.name!r} is a view of {base_name!r}, "
                              "which is not a block port of the module")
        if len(base.shape) == 1:  # a run of elements from ``index``
            if not 0 <= index <= base.size - port.size:
                raise WiringError(f"module {rec.name!r}: port {port.name!r} of shape {port.shape} does not fit "
                                  f"{base_name!r} {base.shape} from element {index}")
            return Slot(base.start + index, port.size, port.shape, port, direction)
        row = int(np.prod(base.shape[1:], dtype=np.int64)) if len(base.shape) > 1 else 1
        if not base.shape or not 0 <= index < base.shape[0] or port.size != row:
            raise WiringError(f"module {rec.name!r}: port {port.name!r} of shape {port.shape} does not fit "
                              f"row {index} of {base_name!r} {base.shape}")
        return Slot(base.start + index * row, row, port.shape, port, direction)



Copies = tuple[tuple[int | slice | np.ndarray, int | slice | np.ndarray], ...]
"""Bus copies ``buf[dst] = buf[src]``: a few index or slice pairs (contiguous runs), or one pair of
index arrays."""


@dataclass(frozen=True)
class Step:
    """One entry of the schedule: a module and the copies its direct inputs need before it steps."""

    record: ModuleRecord
    copies: Copies


class Dispatch(NamedTuple):
    """One entry of the plan as the tick runs it (`CompiledTick`, `PlainTick`): every ``period_ticks``
    ticks from tick ``phase``, make the module's input copies, then call ``step(t_ns, period_ns)``."""

    name: str
    step: Callable[[int, int], None]
    """The module's bound ``step``, taken when the structure is built."""
    period_ns: int
    period_ticks: int
    phase: int
    copies: Copies
    """Copies made on the bus's memoryview (`Structure.delayed`'s form)."""
    gather: Copies
    """Copies made on the bus array: one pair of index arrays (`Structure.delayed_gather`'s form)."""


@dataclass(frozen=True)
class Structure:
    records: tuple[ModuleRecord, ...] = ()
    connections: tuple[Connection, ...] = ()
    layout: BusLayout = field(default_factory=lambda: BusLayout(()))
    plan: tuple[Step, ...] = ()
    delayed: Copies = ()
    """Copies of the delayed connections, made at the start of each tick."""
    dispatch: tuple[Dispatch, ...] = ()
    """The plan flattened for the tick, one entry per module in schedule order."""
    delayed_gather: Copies = ()
    """Copies made on the bus array rather than on its memoryview: one pair of index arrays, when a
    set of connections has too many separate runs (``delayed`` is then empty)."""
    saves: tuple[int, ...] = ()
    """What history saves of each record's module, in record order: `SAVE_STATE` (its ``get_state``),
    `SAVE_PARAMS` (only its parameters: the base ``get_state``) or `SAVE_NONE` (it cannot roll back)."""
    loops: tuple[LoopSpec, ...] = ()
    """Loops declared ``iterate`` (`orchestrator.kernel.iterate`): each is one entry of ``dispatch``,
    its members' steps run by a `LoopRunner` until the loop's values agree."""

    @property
    def runners(self) -> tuple[LoopRunner, ...]:
        """The dispatch entries that run a loop (a world binds them to its bus)."""
        return tuple(e.step for e in self.dispatch if isinstance(e.step, LoopRunner))

    @functools.cached_property
    def compiled(self) -> CompiledTick:
        """The tick of this structure as one generated function (see `orchestrator.kernel.compiled`)."""
        return CompiledTick(self)

    @functools.cached_property
    def output_check(self) -> OutputCheck:
        """Which outputs the world checks are finite after each tick (see `orchestrator.kernel.finite`)."""
        return OutputCheck(self)

    @functools.cached_property
    def plain(self) -> PlainTick:
        """The same tick as `compiled`, run by a plain loop over `dispatch` (no generated code): the one
        to step through in a debugger, and the reference the generated one is tested against."""
        return PlainTick(self)

    def record(self, name: str) -> ModuleRecord | None:
        for rec in self.records:
            if rec.name == name:
                return rec
        return None

    @property
    def names(self) -> list[str]:
        return [rec.name for rec in self.records]

    def driver_of(self, dst: str) -> Connection | None:
        for conn in self.connections:
            if conn.dst == dst:
                return conn
        return None


def build_structure(records: Iterable[ModuleRecord], connections: Iterable[Connection],
                    loops: Iterable[LoopSpec] = ()) -> Structure:
    """Check modules and connections and derive layout and schedule; raises `WiringError`. ``loops``:
    loops declared ``iterate``, whose direct connections among their members may form cycles: each is
    scheduled as one entry (`orchestrator.kernel.iterate`)."""
    records = tuple(records)
    connections = tuple(connections)
    loops = tuple(loops)
    by_name: dict[str, ModuleRecord] = {}
    for rec in records:
        if rec.name in by_name:
            raise WiringError(f"module name {rec.name!r} is used twice")
        by_name[rec.name] = rec
    layout = BusLayout(records)
    for conn in connections:
        _check_connection(conn, layout, by_name)
    _check_single_driver(connections)
    loop_of = check_loops(loops, by_name)
    order = _order(records, connections, by_name, loop_of)
    direct = [c for c in connections if not c.delay and by_name[split_signal(c.src)[0]].module.CAPABILITIES.feedthrough]
    plan, dispatch = [], []
    for item in order:
        members = [by_name[m] for m in item.modules] if isinstance(item, LoopSpec) else [item]
        for rec in members:
            plan.append(Step(rec, _copies(layout, [c for c in direct if split_signal(c.dst)[0] == rec.name])))
        if isinstance(item, LoopSpec):  # the loop's members run by its runner, one entry
            runner, outside = plan_loop(item, by_name, direct, layout.slots)
            first = members[0]
            dispatch.append(Dispatch(item.name, runner, int(first.period_ns), int(first.period_ticks), int(first.phase),
                                     *_split_gather(_copies(layout, outside))))
        else:
            st = plan[-1]
            dispatch.append(Dispatch(item.name, item.module.step, int(item.period_ns), int(item.period_ticks),
                                     int(item.phase), *_split_gather(st.copies)))
    delayed = [c for c in connections if c.delay or not by_name[split_signal(c.src)[0]].module.CAPABILITIES.feedthrough]
    delayed_mv, delayed_gather = _split_gather(_copies(layout, delayed))
    saves = tuple(save_kind(rec.module) for rec in records)
    return Structure(records, connections, layout, tuple(plan), delayed_mv, tuple(dispatch), delayed_gather, saves,
                     loops)


def rebind_structure(structure: Structure, modules: Mapping[str, Module]) -> Structure:
    """``structure`` with each module replaced by ``modules[name]``, a copy of it with the same ports
    (`World.fork`). Nothing of the layout, the checks, the schedule or the copies depends on the module
    objects, only on their names, ports, periods and capabilities, which a copy keeps: the result shares
    them with ``structure`` (the index arrays of the copies are never written) and builds again only
    what holds the modules: the records, the plan's steps, the dispatch entries (their bound ``step``)
    and what history saves of each."""
    records = tuple(dataclasses.replace(rec, module=modules[rec.name]) for rec in structure.records)
    by_name = {rec.name: rec for rec in records}
    for old, new in zip(structure.records, records, strict=True):
        if type(new.module) is not type(old.module):
            raise WiringError(f"module {old.name!r}: its copy is a {type(new.module).__name__}, "
                              f"not a {type(old.module).__name__}")
    plan = tuple(Step(by_name[st.record.name], st.copies) for st in structure.plan)
    dispatch = tuple(entry._replace(step=entry.step.rebound(modules) if isinstance(entry.step, LoopRunner)
                                    else by_name[entry.name].module.step) for entry in structure.dispatch)
    saves = tuple(save_kind(rec.module) for rec in records)
    return Structure(records, structure.connections, structure.layout, plan, structure.delayed, dispatch,
                     structure.delayed_gather, saves, structure.loops)




SAVE_NONE, SAVE_PARAMS, SAVE_STATE = 0, 1, 2


def save_kind(module: Module) -> int:
    if not module.CAPABILITIES.can_rollback:
        return SAVE_NONE
    if type(module).get_state is Module.get_state and "get_state" not in vars(module):
        return SAVE_PARAMS  # the base get_state: nothing to save but the parameters
    return SAVE_STATE


def _split_gather(copies: Copies) -> tuple[Copies, Copies]:
    """(copies the world makes on the bus's memoryview, copies it makes on the array): index arrays
    go to the array, single indices and slices to the memoryview (a copy there costs about half)."""
    if any(isinstance(dst, np.ndarray) for dst, _src in copies):
        return (), copies
    return copies, ()


def _copies(layout: BusLayout, conns: Sequence[Connection], max_runs: int = 8) -> Copies:
    """The copies for ``conns``: contiguous runs merged into slices (a slice copy on the bus's
    memoryview costs a fraction of a fancy-index copy), or one pair of index arrays when there are
    more than ``max_runs`` runs."""
    runs: list[list[int]] = []  # [dst start, src start, size]
    for conn in sorted(conns, key=lambda c: layout.slots[c.dst].start):
        dst, src = layout.slots[conn.dst], layout.slots[conn.src]
        last = runs[-1] if runs else None
        if last is not None and last[0] + last[2] == dst.start and last[1] + last[2] == src.start:
            last[2] += dst.size
        else:
            runs.append([dst.start, src.start, dst.size])
    if len(runs) <= max_runs:  # single values copied by index: cheaper still than a slice of one
        return tuple((d, s) if n == 1 else (slice(d, d + n), slice(s, s + n)) for d, s, n in runs)
    dst_idx = np.concatenate([np.arange(d, d + n) for d, _, n in runs])
    src_idx = np.concatenate([np.arange(s, s + n) for _, s, n in runs])
    return ((dst_idx, src_idx),)


def _check_connection(conn: Connection, layout: BusLayout, by_name: dict[str, ModuleRecord]) -> None:
    for end, want in ((conn.src, "out"), (conn.dst, "in")):
        module, port = split_signal(end)
        if module not in by_name:
            raise WiringError(f"connection {conn}: no module {module!r}" + did_you_mean(module, by_name))
        slot = layout.slots.get(end)
        if slot is None:
            ports = [p.name for p in (by_name[module].outputs if want == "out" else by_name[module].inputs)]
            raise WiringError(f"connection {conn}: module {module!r} has no "
                              f"{'output' if want == 'out' else 'input'} port {port!r}" + did_you_mean(port, ports))
        if slot.direction != want:
            raise WiringError(f"connection {conn}: {end} is an {'input' if want == 'out' else 'output'}; "
                              f"a connection goes from an output to an input")
    src, dst = layout.slots[conn.src], layout.slots[conn.dst]
    if src.shape != dst.shape:
        raise WiringError(f"connection {conn}: shape mismatch, {conn.src} is {src.shape}, {conn.dst} is {dst.shape}")
    if not same_unit(src.port.unit, dst.port.unit):
        raise WiringError(f"connection {conn}: unit mismatch, {conn.src} is in {src.port.unit!r}, "
                          f"{conn.dst} in {dst.port.unit!r}")


def _check_single_driver(connections: Sequence[Connection]) -> None:
    seen: dict[str, Connection] = {}
    for conn in connections:
        if conn.dst in seen:
            raise WiringError(f"input {conn.dst} is driven twice: by {seen[conn.dst].src} and by {conn.src}")
        seen[conn.dst] = conn


def _order(records: tuple[ModuleRecord, ...], connections: tuple[Connection, ...],
           by_name: dict[str, ModuleRecord], loop_of: Mapping[str, LoopSpec]) -> list[ModuleRecord | LoopSpec]:
    """Topological order of direct connections, ties broken by the order modules were added. A loop
    declared ``iterate`` is one node (where its first-added member is); connections among its members
    are left to it."""
    node = {rec.name: loop_of[rec.name].name if rec.name in loop_of else rec.name for rec in records}
    items: dict[str, ModuleRecord | LoopSpec] = {}
    index: dict[str, int] = {}
    for i, rec in enumerate(records):
        if node[rec.name] not in items:
            items[node[rec.name]] = loop_of.get(rec.name, rec)
            index[node[rec.name]] = i
    succ: dict[str, list[tuple[str, Connection]]] = {n: [] for n in items}
    indeg = dict.fromkeys(items, 0)
    for conn in connections:
        src_mod, dst_mod = node[split_signal(conn.src)[0]], node[split_signal(conn.dst)[0]]
        if conn.delay or not by_name[split_signal(conn.src)[0]].module.CAPABILITIES.feedthrough:
            continue
        if src_mod == dst_mod and src_mod in {loop.name for loop in loop_of.values()}:
            continue  # inside a loop: its runner iterates it
        succ[src_mod].append((dst_mod, conn))
        indeg[dst_mod] += 1
    by_index = {i: n for n, i in index.items()}
    ready = [index[n] for n, d in indeg.items() if d == 0]
    heapq.heapify(ready)
    order: list[ModuleRecord | LoopSpec] = []
    while ready:
        name = by_index[heapq.heappop(ready)]
        order.append(items[name])
        for dst_mod, _ in succ[name]:
            indeg[dst_mod] -= 1
            if indeg[dst_mod] == 0:
                heapq.heappush(ready, index[dst_mod])
    if len(order) < len(items):
        raise AlgebraicLoopError(_find_cycle(succ, {n for n, d in indeg.items() if d > 0}))
    return order


def _find_cycle(succ: dict[str, list[tuple[str, Connection]]], stuck: set[str]) -> list[str]:
    """A cycle among the modules left with inputs, as the signals around it.

    Every stuck module has a stuck predecessor, so walking predecessors must meet a cycle.
    """
    pred: dict[str, list[tuple[str, Connection]]] = {n: [] for n in stuck}
    for src, edges in succ.items():
        for dst, conn in edges:
            if src in stuck and dst in stuck:
                pred[dst].append((src, conn))
    node = min(stuck)
    walk: list[tuple[str, Connection]] = []
    seen: dict[str, int] = {}
    while node not in seen:
        seen[node] = len(walk)
        prev, conn = pred[node][0]
        walk.append((prev, conn))
        node = prev
    loop = [conn for _, conn in reversed(walk[seen[node]:])]
    return [str(c.src) + " -> " + str(c.dst) for c in loop] + [split_signal(loop[0].src)[0]]
