"""Strong coupling: a declared loop of feedthrough modules stepped again until its values agree.

The schedule (`orchestrator.kernel.structure`) refuses a cycle of direct connections: each module
steps once a tick on inputs its sources wrote before it, which a cycle cannot give. A loop declared
``iterate`` (`World.iterate`, the scenario's ``iterate:``) is taken into the schedule as one entry, run
by a `LoopRunner`: at each macro step it

1. saves each member's state (`Module.get_state`: rollback belongs to the contract) and the bus;
2. writes its guess ``x`` of the *torn* inputs (those driven by a member that steps at or after the
   member reading them, in the loop's order), steps the members in that order (the other inputs
   copied from members that stepped before, Gauss-Seidel), and reads back ``g(x)``, what the sources
   of the torn inputs gave;
3. stops when ``|g(x) - x| <= tolerance * (1 + |g(x)|)`` (max norms): the members' states and outputs
   are then those of one step on inputs that agree with the outputs;
4. otherwise puts back the saved states and bus and tries again from a better ``x``: first the fixed
   point ``x = g(x)``; once that does not contract (the residual shrinks by less than half), a
   quasi-Newton step on ``F(x) = g(x) - x`` with Broyden's ("good") update of the Jacobian, which
   starts at ``-I`` (the fixed-point step) and is updated at every iteration from the first.

The first guess is what the torn inputs hold from the tick before (a warm start). After
``max_iterations`` runs without agreement the members are put back and `LoopNotConvergedError` is
raised: the world rolls the tick back as for any failed step and raises it, naming the loop, its
residual and the iterations. Each macro step's outcome (`LoopReport`: iterations, residual, converged)
is the runner's ``last``, is logged (``logging``, at debug level) and, when the world has observers, is
a world event ``iterate`` (an MCAP log writes it with the tick).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from .errors import ModuleError, WiringError

if TYPE_CHECKING:
    from .structure import Connection, ModuleRecord, Slot

log = logging.getLogger(__name__)

CONTRACTION = 0.5
"""The fixed-point iteration goes on while each residual is at most this fraction of the last; past it,
Broyden's steps take over."""


@dataclass(frozen=True)
class LoopSpec:
    """A loop declared ``iterate``: its members in the order they step, how close its torn values must
    agree (relative to their size, plus as much absolute) and how many runs of a macro step it may take."""

    name: str
    modules: tuple[str, ...]
    tolerance: float = 1e-9
    max_iterations: int = 50

    def __post_init__(self) -> None:
        if not self.modules or len(set(self.modules)) != len(self.modules):
            raise WiringError(f"loop {self.name!r}: its modules must be distinct and at least one, "
                              f"got {list(self.modules)}")
        if not (isinstance(self.tolerance, (int, float)) and math.isfinite(self.tolerance) and self.tolerance > 0):
            raise WiringError(f"loop {self.name!r}: tolerance must be a number > 0, got {self.tolerance!r}")
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, int) \
                or self.max_iterations < 1:
            raise WiringError(f"loop {self.name!r}: max_iterations must be an integer >= 1, "
                              f"got {self.max_iterations!r}")


class LoopReport(NamedTuple):
    """How one macro step of a loop went."""

    t_ns: int
    iterations: int
    """Runs of the macro step (1: the first guess agreed)."""
    residual: float
    """The largest ``|g(x) - x|`` of the last run."""
    converged: bool


class LoopNotConvergedError(ModuleError):
    """A loop declared ``iterate`` found no values that agree within its tolerance in its iterations;
    the tick was rolled back."""


class TornInput(NamedTuple):
    """An input of the loop torn for the iteration: ``dst`` on the bus is the guess, ``src`` what gives it."""

    dst: slice
    src: slice
    name: str


def check_loops(loops: Sequence[LoopSpec], by_name: dict[str, ModuleRecord]) -> dict[str, LoopSpec]:
    """Module name -> its loop, after checking that every member is present, in one loop only, can roll
    back, is feedthrough and steps at the same ticks as the others."""
    owner: dict[str, LoopSpec] = {}
    names: set[str] = set()
    for loop in loops:
        if loop.name in names or loop.name in by_name:
            raise WiringError(f"loop name {loop.name!r} is used twice (loops and modules share names)")
        names.add(loop.name)
        first = None
        for name in loop.modules:
            rec = by_name.get(name)
            if rec is None:
                raise WiringError(f"loop {loop.name!r}: no module {name!r}")
            if name in owner:
                raise WiringError(f"loop {loop.name!r}: module {name!r} is already in loop {owner[name].name!r}")
            caps = rec.module.CAPABILITIES
            if not caps.can_rollback:
                raise WiringError(f"loop {loop.name!r}: module {name!r} cannot roll back its state, which "
                                  "iterating a step needs")
            if not caps.feedthrough:
                raise WiringError(f"loop {loop.name!r}: module {name!r} is not feedthrough (its outputs "
                                  "come from its state): it breaks the loop itself, leave it out")
            first = first or rec
            if (rec.period_ticks, rec.phase) != (first.period_ticks, first.phase):
                raise WiringError(f"loop {loop.name!r}: module {name!r} steps at other ticks than "
                                  f"{first.name!r}; a loop's modules share one period")
            owner[name] = loop
    return owner


def loops_without(loops: Sequence[LoopSpec], module: str) -> tuple[LoopSpec, ...]:
    """``loops`` with ``module`` taken out (a loop left with no module goes)."""
    out = []
    for loop in loops:
        rest = tuple(m for m in loop.modules if m != module)
        if rest:
            out.append(loop if rest == loop.modules else LoopSpec(loop.name, rest, loop.tolerance,
                                                                  loop.max_iterations))
    return tuple(out)


def _span(slot: Slot) -> slice:
    return slice(slot.start, slot.start + slot.size)


class LoopRunner:
    """One macro step of a loop, as the schedule's entry for it: ``runner(t_ns, dt_ns)`` (see the module
    docstring). Made by the structure (`plan_loop`); bound to a world's bus by `bind`."""

    def __init__(self, spec: LoopSpec, records: Sequence[ModuleRecord],
                 inner: Sequence[Sequence[tuple[slice, slice]]], torn: Sequence[TornInput]):
        self.spec = spec
        self.records = tuple(records)
        self.inner = tuple(tuple(c) for c in inner)
        """The copies made before each member steps: its inputs from members that stepped before it."""
        self.torn = tuple(torn)
        self.buf: np.ndarray | None = None
        self.emit: Callable[..., None] | None = None
        self.last: LoopReport | None = None
        """The outcome of the last macro step run (a rolled-back one included)."""

    def rebound(self, modules: dict[str, Any]) -> LoopRunner:
        """The same runner over copies of its modules (`rebind_structure`: a fork)."""
        records = [dataclasses.replace(rec, module=modules[rec.name]) for rec in self.records]
        return LoopRunner(self.spec, records, self.inner, self.torn)

    def bind(self, buf: np.ndarray, emit: Callable[..., None] | None = None) -> None:
        """Run on the bus ``buf``; ``emit(kind, **detail)`` tells the world's observers of each macro step."""
        self.buf, self.emit = buf, emit

    def __call__(self, t_ns: int, dt_ns: int) -> None:
        buf = self.buf
        if buf is None:
            raise RuntimeError(f"loop {self.spec.name!r} is not bound to a bus")
        steps = [rec.module.step for rec in self.records]
        states = [rec.module.get_state() for rec in self.records]
        saved = buf.copy()
        x = self._read()
        solver = _Solver(len(x))
        report = None
        for k in range(1, self.spec.max_iterations + 1):
            if k > 1:
                for rec, state in zip(self.records, states, strict=True):
                    rec.module.set_state(state)
                buf[:] = saved
            self._run(x, t_ns, dt_ns, steps)
            gx = np.concatenate([buf[t.src] for t in self.torn]) if self.torn else x
            residual = float(np.max(np.abs(gx - x))) if len(x) else 0.0
            if not math.isfinite(residual):
                break
            if residual <= self.spec.tolerance * (1.0 + (float(np.max(np.abs(gx))) if len(x) else 0.0)):
                report = LoopReport(t_ns, k, residual, True)
                break
            x = solver.next(x, gx - x, residual)
        if report is None:
            for rec, state in zip(self.records, states, strict=True):
                rec.module.set_state(state)
            buf[:] = saved
            report = LoopReport(t_ns, k, residual, False)
        self._tell(report)
        if not report.converged:
            raise LoopNotConvergedError(
                self.spec.name, "iterate", None,
                f"its values did not agree within {self.spec.tolerance:g} in {report.iterations} iterations "
                f"(residual {report.residual:.3g} on {', '.join(t.name for t in self.torn)})")

    def _read(self) -> np.ndarray:
        assert self.buf is not None
        parts = [self.buf[t.dst] for t in self.torn]
        return np.concatenate(parts).copy() if parts else np.zeros(0)

    def _run(self, x: np.ndarray, t_ns: int, dt_ns: int, steps: Sequence[Callable[[int, int], None]]) -> None:
        buf = self.buf
        assert buf is not None
        at = 0
        for t in self.torn:
            n = t.dst.stop - t.dst.start
            buf[t.dst] = x[at:at + n]
            at += n
        for copies, step in zip(self.inner, steps, strict=True):
            for dst, src in copies:
                buf[dst] = buf[src]
            step(t_ns, dt_ns)

    def _tell(self, report: LoopReport) -> None:
        before, self.last = self.last, report
        log.debug("loop %s at t=%d ns: %d iterations, residual %.3g, %s", self.spec.name, report.t_ns,
                  report.iterations, report.residual, "converged" if report.converged else "NOT converged")
        same = before is not None and (before.iterations, before.converged) == (report.iterations, report.converged)
        if self.emit is not None and not same:  # an event when the iterations it took change, not every tick
            self.emit("iterate", loop=self.spec.name, iterations=report.iterations, residual=report.residual,
                      converged=report.converged)


class _Solver:
    """The next guess: fixed point while it contracts, then Broyden's quasi-Newton steps on
    ``F(x) = g(x) - x`` (its Jacobian updated at every iteration, from ``-I``)."""

    def __init__(self, size: int):
        self.jacobian = -np.eye(size)
        self.x_prev: np.ndarray | None = None
        self.f_prev: np.ndarray | None = None
        self.res_prev = math.inf
        self.broyden = False

    def next(self, x: np.ndarray, f: np.ndarray, residual: float) -> np.ndarray:
        if self.x_prev is not None and self.f_prev is not None:
            dx, df = x - self.x_prev, f - self.f_prev
            norm2 = float(dx @ dx)
            if norm2 > 0:
                self.jacobian += np.outer(df - self.jacobian @ dx, dx) / norm2
        if residual > CONTRACTION * self.res_prev:
            self.broyden = True
        self.x_prev, self.f_prev, self.res_prev = x, f, residual
        if not self.broyden:
            return x + f  # the fixed point: x = g(x)
        try:
            return x - np.linalg.solve(self.jacobian, f)
        except np.linalg.LinAlgError:
            return x - np.linalg.lstsq(self.jacobian, f, rcond=None)[0]


def plan_loop(spec: LoopSpec, by_name: dict[str, ModuleRecord], direct: Sequence[Connection],
              slots: dict[str, Slot]) -> tuple[LoopRunner, list[Connection]]:
    """The runner of ``spec`` and the direct connections into its members from outside it (copied once,
    before the loop runs). ``direct``: the structure's direct connections (delayed ones excluded, their
    names checked: ``module.port``)."""
    order = {name: i for i, name in enumerate(spec.modules)}
    inner: list[list[tuple[slice, slice]]] = [[] for _ in spec.modules]
    torn: list[TornInput] = []
    outside: list[Connection] = []
    for conn in direct:
        dst_mod, src_mod = conn.dst.partition(".")[0], conn.src.partition(".")[0]
        if dst_mod not in order:
            continue
        if src_mod not in order:
            outside.append(conn)
        elif order[src_mod] < order[dst_mod]:
            inner[order[dst_mod]].append((_span(slots[conn.dst]), _span(slots[conn.src])))
        else:
            torn.append(TornInput(_span(slots[conn.dst]), _span(slots[conn.src]), conn.dst))
    records = [by_name[name] for name in spec.modules]
    return LoopRunner(spec, records, inner, sorted(torn, key=lambda t: t.dst.start)), outside
