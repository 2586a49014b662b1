"""The check that every module's outputs stay finite, made after each tick at the cost of one sum.

A NaN or an infinity on the bus spreads to whatever reads it, ticks later; the world finds one at the
tick it appears. After a tick, it adds up the outputs of every module that declares them finite
(`Capabilities.finite_outputs`, the default): a sum that is not finite means some
value is not, and only then does it look which module and port, and fail the tick
(`NonFiniteOutputError`; the world rolls it back).

Outputs lie on the bus module by module, with each module's inputs before its outputs. To add them up
in few calls, the checked outputs are merged into spans across the slots between them that should hold
finite numbers too: inputs that start finite and are driven by a checked output or by nothing. An
input that starts NaN (a body's velocity: unset) or is driven by a module that opted out (a ZMP with
no contact) ends a span, so the values it holds by design never make a check look further. Should such
a value be there all the same (NaN written into an input by hand), the sum is not finite, the search
finds every checked output finite, and the tick goes on: slower, never wrong.

A span of up to `INLINE` values is added up by the tick itself (``mv[7] + mv[8]``, written out in the
generated tick: a few tens of ns), one of up to `SMALL` values by Python's `sum` over a memoryview
(under 0.1 us), a longer one by a dot product with ones (about 0.3 us for the humanoid's 730 values),
and one longer than `LARGE` (an image) by numpy's reduction on one thread. The tick adds the spans'
sums together and tests the total once (`orchestrator.kernel.compiled`). A sum is infinite or NaN when
a value is (a sum of finite values that overflows is infinite too: the search then finds nothing, and
the tick goes on); the tick tests it with comparisons, which never warn.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import NonFiniteOutputError

if TYPE_CHECKING:
    from .structure import Structure

INLINE = 4
"""Spans of at most this many values are added up in the generated tick itself, value by value."""

SMALL = 24
"""Spans of at most this many values are summed over a memoryview; longer ones by a dot product."""

LARGE = 8192
"""Spans longer than this (images) are summed by numpy's own reduction: a BLAS dot product over 230k
values started OpenBLAS's threads, which fought over the cores (about 6 ms a tick with a stereo
camera on a 2-core machine, against tens of microseconds summed on one thread)."""

Probe = tuple[Callable[[Any], float], Any]
"""One span as the world checks it, ``add(values)``: (`sum`, a memoryview of the span) or (the span's
bound ``dot``, ones)."""


class OutputCheck:
    """The checked outputs of one structure: ``spans`` (start, stop) on its bus, and ``ports`` (module,
    port, start, stop) of each checked output, for the search after a sum that is not finite."""

    def __init__(self, structure: Structure):
        layout = structure.layout
        checked = {rec.name for rec in structure.records if rec.module.CAPABILITIES.finite_outputs}
        self.ports: tuple[tuple[str, str, int, int], ...] = tuple(
            (rec.name, port.name, slot.start, slot.start + slot.size)
            for rec in structure.records if rec.name in checked
            for port in rec.outputs if port.view_of is None and (slot := layout.slots[f"{rec.name}.{port.name}"]).size)
        driver = {conn.dst: conn.src for conn in structure.connections}
        spans: list[list[int]] = []
        safe_to = -1  # the bus is finite by design from the end of the last span up to here
        for rec in structure.records:
            own = layout.modules[rec.name]
            for port in rec.inputs:
                if port.view_of is not None:
                    continue
                slot = layout.slots[f"{rec.name}.{port.name}"]
                src = driver.get(f"{rec.name}.{port.name}")
                finite_start = port.start is None or bool(np.all(np.isfinite(np.asarray(port.start, dtype=float))))
                if finite_start and (src is None or src.partition(".")[0] in checked):
                    if safe_to == slot.start:
                        safe_to = slot.start + slot.size
                else:
                    safe_to = -1
            run = own.outputs_flat
            if run is None or run.start == run.stop:
                continue
            if rec.name not in checked:
                safe_to = -1
                continue
            if spans and safe_to == run.start:
                spans[-1][1] = run.stop
            else:
                spans.append([run.start, run.stop])
            safe_to = run.stop
        self.spans: tuple[tuple[int, int], ...] = tuple((a, b) for a, b in spans)

    def probes(self, buf: np.ndarray, mv: memoryview) -> tuple[Probe, ...]:
        """The spans on the bus ``buf`` (``mv`` its memoryview), as the world checks them each tick."""
        return tuple((sum, mv[a:b]) if b - a <= SMALL else (buf[a:b].dot, np.ones(b - a)) if b - a <= LARGE
                     else (np.add.reduce, buf[a:b]) for a, b in self.spans)

    def search(self, buf: np.ndarray, tick: int) -> None:
        """Raise `NonFiniteOutputError` for the first checked output on ``buf`` that is not finite (after
        a sum that was not); return when there is none."""
        for module, port, a, b in self.ports:
            values = buf[a:b]
            bad = np.flatnonzero(~np.isfinite(values))
            if len(bad):
                value = float(values[bad[0]])
                what = "NaN" if np.isnan(value) else f"{value:g}"
                where = f" (element {bad[0] + 1} of {b - a}; {len(bad)} not finite)" if b - a > 1 else ""
                raise NonFiniteOutputError(
                    module, "step", tick, f"output {port!r} is {what}{where}; outputs must be finite numbers "
                    "(a module whose outputs may be NaN or infinite by design declares "
                    "Capabilities(finite_outputs=False))", port=port)
