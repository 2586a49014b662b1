"""Drive: ticks with inputs driven from arrays and signals recorded into arrays (`World.run`, as FMPy's
Input and Recorder), and the futures a brain imagined, kept for the log (`World.imagine`)."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .. import edits
from ..errors import DynabrainError, ModuleError, WiringError
from ..observers import Imagined
from .context import Context
from .names import Names
from .stepper import Stepper
from .timeline import Timeline

_IMAGINED_NAME = re.compile(r"[A-Za-z0-9_.-]{1,100}")


class Drive:
    """Driven runs and imagined futures of one world (see the module docstring). The caller holds the
    world lock."""

    def __init__(self, ctx: Context, stepper: Stepper, timeline: Timeline, names: Names):
        self.ctx = ctx
        self.stepper = stepper
        self.timeline = timeline
        self.names = names

    def run(self, ticks: int, inputs: Mapping[str, Any], record: Sequence[str]) -> dict[str, np.ndarray]:
        ctx, names = self.ctx, self.names
        drives = self.drives(inputs, ticks)
        out = {name: np.full((ticks, *names.signal_slot(name, "run() record").shape), np.nan) for name in record}
        # rows cross as bytes (memoryview copies): each input's values as one bytes object, whose row k
        # is written into the bus and handed to history as it is (`History.written`)
        given = [(values.tobytes(), 8 * values.shape[1], values, name) for values, name in drives]
        rows = [(memoryview(out[name]).cast("B"), 8 * out[name][0].size, name) for name in out]
        structure, slots, bus = None, [], ctx.mv
        k = 0
        try:
            for k in range(ticks):
                if ctx.structure is not structure:  # (an event may change it): find the slots again
                    structure, bus = ctx.structure, ctx.mv.cast("B")
                    slots = [(names.input_slot(name), raw, size, values, name) for raw, size, values, name in given]
                    recs = [(8 * names.signal_slot(name, "run() record").start, size, row) for row, size, name in rows]
                if slots:
                    spans = []
                    for slot, raw, size, values, name in slots:
                        row = raw[k * size:k * size + size]
                        bus[8 * slot.start:8 * slot.start + size] = row
                        spans.append((slot.start, row))
                        if ctx.observers:
                            ctx.tell(edits.Set(name, values[k].reshape(slot.shape).tolist()))
                    self.timeline.keep_inputs(spans)
                self.stepper.steps(1)
                for at, size, row in recs:
                    row[k * size:k * size + size] = bus[at:at + size]
        except ModuleError as err:
            err.recorded, err.ticks_done = out, k
            raise
        return out

    def drives(self, inputs: Mapping[str, Any], ticks: int) -> list[tuple[np.ndarray, str]]:
        """Each input's values as rows of ``(ticks, size)``, checked against its port, with its full name."""
        drives = []
        for name, values in inputs.items():
            full = self.names.settable(name)
            if not isinstance(full, str):
                raise WiringError(f"run(): {name!r} is a parameter; inputs are input ports (set a parameter with set)")
            slot = self.ctx.structure.layout.slots[full]
            arr = np.asarray(values, dtype=np.float64)
            if arr.shape != (ticks, *slot.shape):
                raise WiringError(f"run(): the values for {full} have shape {arr.shape}; {ticks} ticks of a port of "
                                  f"shape {slot.shape} need {(ticks, *slot.shape)}")
            drives.append((arr.reshape(ticks, -1), full))
        return drives

    # -- imagined futures -------------------------------------------------------------------------------
    @staticmethod
    def _check_imagined(name: str, start_tick: int, signals: Mapping[str, Any], branch: int) -> None:
        if not isinstance(name, str) or not _IMAGINED_NAME.fullmatch(name):
            raise DynabrainError(f"imagine: the name {name!r} must be letters, digits, '_', '-' or '.'")
        for what, value in (("start_tick", start_tick), ("branch", branch)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise DynabrainError(f"imagine({name!r}): {what} must be an integer >= 0, got {value!r}")
        if not isinstance(signals, Mapping) or not signals:
            raise DynabrainError(f"imagine({name!r}): signals is a mapping of signal -> values (ticks, *shape)")

    def imagine(self, name: str, start_tick: int, signals: Mapping[str, Any], branch: int) -> Imagined:
        self._check_imagined(name, start_tick, signals, branch)
        ctx, names = self.ctx, self.names
        values: dict[str, np.ndarray] = {}
        units: dict[str, str] = {}
        ticks = None
        for given, rows in signals.items():
            try:
                arr = np.array(rows, dtype=np.float64)  # a copy: the caller may change its array
            except (TypeError, ValueError) as exc:
                raise DynabrainError(f"imagine({name!r}): the values of {given} are not numbers: {exc}") from None
            slot = names.resolve_signal(given) if isinstance(given, str) else None
            full = names.full_signal_name(given) if slot is not None else given
            if slot is not None and arr.shape[1:] != slot.shape:
                raise WiringError(f"imagine({name!r}): the values of {full} have shape {arr.shape}; ticks of a "
                                  f"signal of shape {slot.shape} need (ticks, {', '.join(map(str, slot.shape))})")
            if arr.ndim == 0 or (ticks is not None and len(arr) != ticks) or len(arr) == 0:
                raise DynabrainError(f"imagine({name!r}): every signal needs the same number (>= 1) of rows, "
                                     f"one per tick; {given} has shape {arr.shape}")
            ticks = len(arr)
            arr.flags.writeable = False
            values[str(full)] = arr
            units[str(full)] = slot.port.unit if slot is not None else ""
        imagined = Imagined(name, int(branch), int(start_tick), ctx.dt_ns, values, units, ctx.tick)
        for obs in ctx.observers:
            obs.on_imagined(ctx.view, imagined)
        return imagined
