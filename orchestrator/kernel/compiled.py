"""A structure's tick as one generated Python function (the schedule unrolled), the same tick as a plain
loop, and history's state saver as another generated function.

The kernel's hot loop walks the schedule every tick: for each module, test its phase, make the copies
its inputs need, call its step. Walking a list of entries (`PlainTick`) costs 0.1 to 0.2 us per
module and tick more (attribute loads, empty loops, branches) on top of the step itself. For each structure,
`CompiledTick` writes that walk out as straight-line source, one statement per copy and per step,
with the steps and index arrays bound as fast locals, and compiles it; its last line is the check that
the outputs are finite (`orchestrator.kernel.finite`: the spans' sums added up, a short span written
out value by value, and tested once). A structure changes only on an edit (add, remove, connect, ...),
and keeps its function (`Structure.compiled`), so one compilation serves every tick of the structure,
rollbacks across edits included. A world runs it bound to its bus (`CompiledTick.bind`: the same code
with the bus and the spans summed on it as defaults too), one call a tick.

Generated code stays debuggable:

- its source is registered in `linecache` under a name of its own (``<dynabrain tick 7>``), so a
  traceback through it shows the line that ran (``step_servo(t_ns, 2000000)``) and pdb can list it;
  the entry goes when the generated code is garbage collected (a kept traceback keeps it);
- its locals are named after what they hold: ``step_<module>`` for a module's step,
  ``<module>_in_dst`` / ``<module>_in_src`` for the indices of its input copies, ``delayed_dst`` /
  ``delayed_src`` for the delayed connections' (names sanitised to identifiers, made unique);
- `PlainTick` runs the same entries in a plain loop, with no generated code: ``World(compiled=False)``
  or ``DYNABRAIN_COMPILED=0`` in the environment. Use it to step through a tick in a debugger or to
  rule the generated code out; the states are bit-identical to the compiled tick's.

The generated function has one line per module step (with its copies just before), so an exception's
traceback says which module was running: `CompiledTick.failed_module` reads it back. ``source``
keeps the text, for whoever wants to see what a tick does.

History's `state_saver` is the same idea for the states saved after each tick: one generated
function returns every module's state as a tuple, calling ``get_state`` only where a step may have
changed the state and holding the others as values, and another pushes history's entry for a tick (the
bus's bytes, the parameters and those states) in one call.
"""

from __future__ import annotations

import itertools
import linecache
import os
import re
import weakref
from collections.abc import Callable, Sequence
from types import CodeType, FunctionType, TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import DynabrainError
from .finite import INLINE, Probe
from .module import Module

_NO_FUSE = Module.fuse.__func__  # type: ignore[attr-defined]

if TYPE_CHECKING:
    from .module import Fused
    from .structure import Copies, Dispatch, Structure

ENV_SWITCH = "DYNABRAIN_COMPILED"
"""The environment variable that picks the tick of every World made without ``compiled=``: ``0``
(or ``false``, ``no``, ``off``) runs the plain loop, ``1`` (or unset) the generated code."""

_OFF, _ON = ("0", "false", "no", "off"), ("", "1", "true", "yes", "on")
_CONNECTIONS = "connections"  # who runs the delayed copies, for `failed_module`
_numbers = itertools.count(1)  # makes each generated source's file name unique


def compiled_by_default() -> bool:
    """Whether a World made without ``compiled=`` generates its tick (`ENV_SWITCH`)."""
    value = os.environ.get(ENV_SWITCH, "").strip().lower()
    if value not in _OFF + _ON:
        raise DynabrainError(f"{ENV_SWITCH}={os.environ[ENV_SWITCH]!r}: use 0 (the plain tick) or 1 (generated)")
    return value not in _OFF


def _define(source: str, kind: str, name: str, values: dict[str, Any]) -> tuple[str, Callable[..., Any]]:
    """Compile and run ``source`` (with ``values`` as its globals) under a file name of its own, with
    the source in `linecache` (an entry with no modification time, which `linecache.checkcache` leaves
    alone); returns the file name and the function ``name`` the source defines. The caller ties the
    entry's life to the code with `_forget`."""
    filename = f"<dynabrain {kind} {next(_numbers)}>"
    code = compile(source, filename, "exec")
    linecache.cache[filename] = (len(source), None, source.splitlines(keepends=True), filename)
    namespace = dict(values)
    exec(code, namespace)  # our own source, generated from the structure's plan
    return filename, namespace.pop(name)  # popped: the function and its globals make no cycle


def _forget(codes: Sequence[CodeType], filename: str) -> None:
    """Drop ``filename``'s source from `linecache` when every code object of ``codes`` is collected. A
    code object lives as long as a function made from it or a frame that ran it (in a kept traceback)
    does."""
    left = [len(codes)]

    def gone() -> None:
        left[0] -= 1
        if not left[0]:
            linecache.cache.pop(filename, None)

    for code in codes:
        weakref.finalize(code, gone)


def _identifier(name: str) -> str:
    """``name`` with every character an identifier cannot hold made ``_`` (``l-foot`` -> ``l_foot``)."""
    return re.sub(r"\W", "_", name, flags=re.ASCII)


class CompiledTick:
    """``run(n, t_ns, mv, buf, *probes)`` steps every module due at tick ``n`` (time ``t_ns``) on the bus
    ``buf`` (and ``mv``, its memoryview), with the delayed copies first and each module's input copies
    before its step, then checks that the outputs are finite (`orchestrator.kernel.finite`; ``probes``:
    the add and values of each span it sums by a call): the structure's plan as one generated function,
    the fast way (the World's default). A world runs ``bind(mv, buf)``, the same function with all
    of that bound, as ``tick(n, t_ns)``. ``source`` is its text; ``filename`` the name its traceback
    lines and `linecache` entry have."""

    def __init__(self, structure: Structure):
        env: dict[str, Any] = {}  # local name -> value, bound as defaults of the function
        taken = {"n", "t_ns", "mv", "buf", "tick"}
        lines: list[str] = []
        owners: list[str | Fused | None] = []  # the module whose step (or copies) each line runs

        def local(base: str, value: Any) -> str:
            if not base.isidentifier():
                base = f"_{base}"  # a module name that begins with a digit
            name, k = base, 2
            while name in taken:
                name, k = f"{base}_{k}", k + 1
            taken.add(name)
            env[name] = value
            return name

        def operand(value: Any, base: str) -> str:
            if isinstance(value, (int, np.integer)):
                return str(int(value))
            return local(base, value)

        def copies(mv_copies: Copies, gather: Copies, base: str) -> list[str]:
            out = [f"mv[{operand(dst, f'{base}_dst')}] = mv[{operand(src, f'{base}_src')}]" for dst, src in mv_copies]
            out += [f"buf[{operand(dst, f'{base}_dst')}] = buf[{operand(src, f'{base}_src')}]" for dst, src in gather]
            return out

        delayed = copies(structure.delayed, structure.delayed_gather, "delayed")
        if delayed:
            lines.append("; ".join(delayed))
            owners.append(_CONNECTIONS)
        self._fused: dict[str, Fused] = {}  # local name -> modules stepped as one (bound by `bind`)
        for run in _runs(structure.dispatch):
            fused = _fuse(run) if len(run) > 1 else None
            if fused is not None:
                first, last = _identifier(run[0].name), _identifier(run[-1].name)
                name = local(f"fused_{first}_{last}", fused)
                self._fused[name] = fused
                items: list[tuple[Dispatch, str, str | Fused]] = [(run[0], f"{name}(t_ns, {run[0].period_ns})", fused)]
            else:
                items = []
                for entry in run:
                    ident = _identifier(entry.name)
                    step = local(f"step_{ident}", entry.step)
                    call = f"{step}(t_ns, {entry.period_ns})"
                    items.append((entry, "; ".join([*copies(entry.copies, entry.gather, f"{ident}_in"), call]),
                                  entry.name))
            for entry, body, owner in items:
                if entry.period_ticks != 1:
                    body = f"if not (n - {entry.phase}) % {entry.period_ticks}: {body}"
                lines.append(body)
                owners.append(owner)
        # the finite-output check: each span's sum (a short one written out), added up, tested once
        self._check = structure.output_check
        terms: list[str] = []
        probes: list[str] = []  # the parameters `bind` fills from `OutputCheck.probes`, two per span summed by a call
        self._called: list[int] = []  # ... and which spans they are
        for k, (a, b) in enumerate(self._check.spans):
            if b - a <= INLINE:
                terms += [f"mv[{i}]" for i in range(a, b)]
                continue
            add, values = f"add_span{k}", f"span{k}"
            taken.update((add, values))
            probes += [add, values]
            terms.append(f"{add}({values})")
            self._called.append(k)
        if terms:  # 1e309 is inf: a total that is NaN or infinite means some value is not finite
            search = local("search_outputs", self._check.search)
            lines.append(f"if not -1e309 < {' + '.join(terms)} < 1e309: {search}(buf, n)")
            owners.append(None)
        # the values are defaults of `tick`, so they are fast locals in it; one default a line
        indent = " " * len("def tick(")
        params = ["n, t_ns, mv, buf", *probes]
        head = [f"def tick({', '.join(params)}" + ("," if env else "):") + "\n"]
        head += [f"{indent}{name}={name}" + (",\n" if i < len(env) - 1 else "):\n") for i, name in enumerate(env)]
        body = [f"    {line}\n" for line in lines] or ["    pass\n"]
        self.source = "".join([*head, *body])
        self.filename, self.run = _define(self.source, "tick", "tick", env)
        _forget([self.run.__code__], self.filename)
        first = len(head) + 1  # the line number of lines[0]
        self._owner: dict[int, str | Fused] = {first + i: owner for i, owner in enumerate(owners) if owner is not None}

    def bind(self, mv: memoryview, buf: np.ndarray) -> Callable[[int, int], None]:
        """The tick on the bus ``buf`` (``mv``, its memoryview): ``tick(n, t_ns)``, the same code as `run`
        with the bus and the output check's spans on it bound as defaults (fast locals)."""
        run = self.run
        probes = self._check.probes(buf, mv)
        names = run.__code__.co_varnames[len(run.__code__.co_varnames) - len(run.__defaults__ or ()):
                                          run.__code__.co_argcount]
        defaults = [self._fused[n].bind(buf) if n in self._fused else v
                    for n, v in zip(names, run.__defaults__ or (), strict=True)]
        bound = (mv, buf, *(value for k in self._called for value in probes[k]), *defaults)
        return FunctionType(run.__code__, run.__globals__, run.__name__, bound)

    def failed_module(self, tb: TracebackType | None) -> str | None:
        """The module whose step raised (``"connections"`` for the delayed copies), from the traceback
        of an exception out of `run`: the line of the generated function it went through."""
        while tb is not None:
            if tb.tb_frame.f_code.co_filename == self.filename:
                owner = self._owner.get(tb.tb_lineno)
                return owner if owner is None or isinstance(owner, str) else owner.failing
            tb = tb.tb_next
        return None


def _runs(dispatch: Sequence[Dispatch]) -> list[list[Dispatch]]:
    """The entries in schedule order, cut into runs that `Module.fuse` may step as one: next to each
    other, modules whose classes share one `Module.fuse` (other than the default), due at the same
    ticks, with their copies made on the memoryview (single values or plain slices). Every other entry
    is a run of its own. The fuse of the run's first class decides (and may decline: None)."""
    runs: list[list[Dispatch]] = []
    key = None  # what the last run shares, when it may grow
    for entry in dispatch:
        module = getattr(entry.step, "__self__", None)
        fuse = getattr(type(module).fuse, "__func__", None) if module is not None else None
        fuses = (fuse is not None and fuse is not _NO_FUSE and not entry.gather
                 and all(isinstance(i, (int, np.integer)) or (isinstance(i, slice) and i.step in (None, 1))
                         for pair in entry.copies for i in pair))
        here = (fuse, entry.period_ns, entry.period_ticks, entry.phase) if fuses else None
        if here is not None and here == key:
            runs[-1].append(entry)
        else:
            runs.append([entry])
        key = here
    return runs


def _fuse(run: Sequence[Dispatch]) -> Fused | None:
    """The run's modules stepped as one, when their class says how (`Module.fuse`)."""
    members = [e.step.__self__ for e in run]  # type: ignore[attr-defined]
    return type(members[0]).fuse(members, [e.copies for e in run])


class PlainTick:
    """The same tick as `CompiledTick` (same entries, same order, same copies: bit-identical states),
    run by a plain loop over the structure's `Structure.dispatch` with no generated code. It costs 0.1
    to 0.2 us more per module and tick (measured with 1 to 20 trivial modules). Use it for debugging
    (``World(compiled=False)`` or ``DYNABRAIN_COMPILED=0``): breakpoints in it, stepping through a tick
    module by module, ruling the generated code out when something looks wrong."""

    def __init__(self, structure: Structure):
        self.delayed = structure.delayed
        self.delayed_gather = structure.delayed_gather
        self.dispatch = structure.dispatch
        self.check = structure.output_check
        self.running: str | None = None
        """The module whose copies or step run now (``"connections"``: the delayed copies); after an
        exception out of `run`, the one that raised."""

    def run(self, n: int, t_ns: int, mv: memoryview, buf: np.ndarray, probes: Sequence[Probe] = ()) -> None:
        self.running = _CONNECTIONS
        for dst, src in self.delayed:
            mv[dst] = mv[src]
        for dst, src in self.delayed_gather:
            buf[dst] = buf[src]
        for entry in self.dispatch:
            if (n - entry.phase) % entry.period_ticks:
                continue  # not due at this tick
            self.running = entry.name
            for dst, src in entry.copies:
                mv[dst] = mv[src]
            for dst, src in entry.gather:
                buf[dst] = buf[src]
            entry.step(t_ns, entry.period_ns)
        self.running = None
        for add, values in probes:  # are the outputs finite? (`orchestrator.kernel.finite`)
            total = add(values)
            if not -1e309 < total < 1e309:  # 1e309 is inf: NaN or inf, some value is not finite
                self.check.search(buf, n)

    def bind(self, mv: memoryview, buf: np.ndarray) -> Callable[[int, int], None]:
        """`run` on the bus ``buf`` (``mv``, its memoryview) and the output check's spans on it, as
        ``tick(n, t_ns)`` (`CompiledTick.bind`'s form)."""
        run, probes = self.run, self.check.probes(buf, mv)

        def tick(n: int, t_ns: int) -> None:
            run(n, t_ns, mv, buf, probes)

        return tick

    def failed_module(self, tb: TracebackType | None) -> str | None:
        """The module whose step raised, from the traceback of an exception out of `run`: the marker
        `run` left (None when the traceback does not go through this tick's `run`)."""
        while tb is not None:
            frame = tb.tb_frame
            if frame.f_code is PlainTick.run.__code__ and frame.f_locals.get("self") is self:
                return self.running
            tb = tb.tb_next
        return None


_SAVERS: dict[tuple[tuple[bool, ...], bool], Callable[..., tuple[Callable[[], tuple], Callable[[int], None]]]] = {}


def state_saver(entries: Sequence[tuple[bool, Any]], append: Callable[[tuple | int], None], copy: Callable[[], Any],
                head: tuple[int, Any, Any], every: int = 1) -> tuple[Callable[[], tuple], Callable[[int], None]]:
    """``(save, record)``: ``save()`` returns every module's state as one tuple, in one call (``entries``
    are ``(True, get_state)`` for a state to ask for at each call, ``(False, state)`` for one kept as
    is); ``record(tick)`` hands ``append`` history's entry for ``tick``, ``(world_id, tick, structure,
    copy(), params, 0, *save())`` (`WorldState.entry`'s form; ``head`` is ``(world_id, structure,
    params)``, ``copy`` makes the bus's copy), as one call too: the world's capture after each tick.
    With keyframes (``every`` > 1, `History`), ``record`` hands the entry at ticks that are multiples of
    ``every`` and the tick's number alone at the others. The generated code depends only on which entries
    are calls and on keyframes or not, and is made once per such pattern; its source is in `linecache`
    (``<dynabrain state saver 8>``) while a saver made from it lives."""
    pattern = tuple(bool(call) for call, _value in entries)
    make = _SAVERS.get((pattern, every > 1))
    if make is None:
        names = [f"get_state{i}" if call else f"kept{i}" for i, call in enumerate(pattern)]
        items = "".join(f"{n}(), " if call else f"{n}, " for n, call in zip(names, pattern, strict=True))
        bound = "".join(f"{n}={n}, " for n in names)
        between = "        if tick % every:\n            return append(tick)\n" if every > 1 else ""
        source = (f"def make({''.join(n + ', ' for n in names)}append, copy, world_id, structure, params, every):\n"
                  f"    def save({bound}):\n"
                  f"        return ({items})\n"
                  f"    def record(tick, {bound}append=append, copy=copy, world_id=world_id, structure=structure,"
                  " params=params, every=every):\n"
                  f"{between}"
                  f"        append((world_id, tick, structure, copy(), params, 0, {items}))\n"
                  "    return save, record\n")
        filename, make = _define(source, "state saver", "make", {})
        # `make` holds both functions' code, and so does every saver made from it
        _forget([c for c in make.__code__.co_consts if isinstance(c, CodeType)], filename)
        if len(_SAVERS) >= 256:  # patterns come and go with edits: keep the cache small
            _SAVERS.clear()
        _SAVERS[pattern, every > 1] = make
    return make(*(value for _call, value in entries), append, copy, *head, every)
