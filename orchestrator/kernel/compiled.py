"""A structure's tick as one generated Python function (the schedule unrolled), and history's state
saver as another.

The kernel's hot loop walks the schedule every tick: for each module, test its phase, make the copies
its inputs need, call its step. Walking a list of entries costs a few hundred nanoseconds per module
and tick (unpacking, empty loops, branches) on top of the step itself. For each structure,
`CompiledTick` writes that walk out as straight-line source, one statement per copy and per step,
with the steps and index arrays bound as fast locals, and compiles it. A structure changes only on an
edit (add, remove, connect, ...), and keeps its function (`Structure.compiled`), so one compilation
serves every tick of the structure, rollbacks across edits included.

The generated function has one line per module step (with its copies just before), so an exception's
traceback says which module was running: `CompiledTick.failed_module` reads it back. ``source``
keeps the text, for whoever wants to see what a tick does.

History's `state_saver` is the same idea for the states saved after each tick: one generated
function returns every module's state as a tuple, calling ``get_state`` only where a step may have
changed the state and holding the others as values.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from .structure import Copies, Structure

_FILENAME = "<dynabrain tick>"


class CompiledTick:
    """``run(n, t_ns, mv, buf)`` steps every module due at tick ``n`` (time ``t_ns``) on the bus ``buf``
    (and ``mv``, its memoryview), with the delayed copies first and each module's input copies before
    its step."""

    def __init__(self, structure: Structure):
        env: dict[str, Any] = {}
        lines: list[str] = []
        self._owner: dict[int, str] = {}  # line number -> module whose step (or copies) runs there

        def constant(value: Any) -> str:
            if isinstance(value, (int, np.integer)):
                return str(int(value))
            name = f"k{len(env)}"
            env[name] = value
            return name

        def copies(mv_copies: Copies, gather: Copies) -> list[str]:
            out = [f"mv[{constant(dst)}] = mv[{constant(src)}]" for dst, src in mv_copies]
            out += [f"buf[{constant(dst)}] = buf[{constant(src)}]" for dst, src in gather]
            return out

        delayed = copies(structure.delayed, structure.delayed_gather)
        if delayed:
            lines.append("; ".join(delayed))
            self._owner[len(lines)] = "connections"
        for i, (name, step, period_ns, period_ticks, phase, mv_copies, gather) in enumerate(structure.dispatch):
            env[f"s{i}"] = step
            body = "; ".join([*copies(mv_copies, gather), f"s{i}(t_ns, {int(period_ns)})"])
            if period_ticks != 1:
                body = f"if not (n - {int(phase)}) % {int(period_ticks)}: {body}"
            lines.append(body)
            self._owner[len(lines)] = name
        bound = "".join(f", {k}={k}" for k in env)  # defaults: fast locals in the function
        head = f"def make({', '.join(env)}):\n    def tick(n, t_ns, mv, buf{bound}):\n"
        body = "".join(f"        {line}\n" for line in lines) or "        pass\n"
        self.source = head + body + "    return tick\n"
        code = compile(self.source, _FILENAME, "exec")
        namespace: dict[str, Any] = {}
        exec(code, namespace)  # our own source, generated from the structure's plan
        self.run = namespace["make"](**env)
        self._first = 3  # `lines[0]` is line 3 of the source

    def failed_module(self, tb: TracebackType | None) -> str | None:
        """The module whose step raised, from the traceback of an exception out of `run`."""
        while tb is not None:
            if tb.tb_frame.f_code.co_filename == _FILENAME:
                return self._owner.get(tb.tb_lineno - self._first + 1)
            tb = tb.tb_next
        return None


_SAVERS: dict[tuple[bool, ...], Callable[..., Callable[[], tuple]]] = {}


def state_saver(entries: Sequence[tuple[bool, Any]]) -> Callable[[], tuple]:
    """A function that returns every module's state as one tuple, in one call: ``entries`` are
    ``(True, get_state)`` for a state to ask for at each call, ``(False, state)`` for one kept as is.
    The generated code depends only on which entries are calls, and is made once per such pattern."""
    pattern = tuple(bool(call) for call, _value in entries)
    make = _SAVERS.get(pattern)
    if make is None:
        names = [f"v{i}" for i in range(len(pattern))]
        items = "".join(f"{n}(), " if call else f"{n}, " for n, call in zip(names, pattern, strict=True))
        bound = ", ".join(f"{n}={n}" for n in names)
        source = (f"def make({', '.join(names)}):\n    def save({bound}):\n        return ({items})\n"
                  "    return save\n")
        namespace: dict[str, Any] = {}
        exec(compile(source, "<dynabrain state saver>", "exec"), namespace)  # our own generated source
        if len(_SAVERS) >= 256:  # patterns come and go with edits: keep the cache small
            _SAVERS.clear()
        make = _SAVERS[pattern] = namespace["make"]
    return make(*(value for _call, value in entries))
