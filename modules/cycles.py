"""A probe for oscillations: counts the cycles of a signal and records the amplitude of each swing.

The meter finds the signal's turning points (a maximum is confirmed once the signal has fallen
``deadband`` below it, a minimum once it has risen ``deadband`` above it), so it needs no centre and
follows an oscillation whose mean drifts. A *swing* goes from one turning point to the next; its
amplitude is half its height (half the peak-to-peak). A full cycle is two swings.

Input ``x`` (unit: the ``unit`` parameter; connect e.g. ``core.<hinge>.q``). Outputs: ``swings``
(swings completed: the motion before the first turning point does not count), ``cycles`` (full
cycles, ``swings // 2``), ``amplitude`` (of the last swing, NaN before the first), ``peaks``
(``max_peaks``,): the amplitudes of the swings in order, NaN until reached.
"""

from __future__ import annotations

import math

import numpy as np

from dynabrain.orchestrator.kernel.module import Capabilities, Module, Param, Port


class CycleMeter(Module):
    """Cycles and swing amplitudes of an oscillating signal (see the module docstring)."""

    CAPABILITIES = Capabilities(finite_outputs=False)  # NaN: no swing measured yet

    PARAMS = (
        Param("unit", "rad", doc="unit of the signal"),
        Param("deadband", 0.01, doc="how far the signal must come back from a turning point to confirm it"),
        Param("max_peaks", 32, doc="how many swing amplitudes are recorded"),
    )

    def inputs(self) -> list[Port]:
        return [Port("x", (), self.params["unit"], "the oscillating signal")]

    def outputs(self) -> list[Port]:
        unit = self.params["unit"]
        return [Port("cycles", (), "1"), Port("swings", (), "1"), Port("amplitude", (), unit),
                Port("peaks", (self.params["max_peaks"],), unit)]

    def start(self, t_ns: int) -> None:
        self._dir, self._start, self._extreme, self._last, self._swings = 0, math.nan, math.nan, math.nan, 0
        self.out["peaks"][...] = np.nan
        self.out["amplitude"][...] = np.nan
        self.out["cycles"][...] = 0
        self.out["swings"][...] = 0

    def step(self, t_ns: int, dt_ns: int) -> None:
        x = float(self.inp["x"])
        if not math.isfinite(x):
            return
        band = self.params["deadband"]
        if self._dir == 0:  # not moving yet: wait until the signal leaves its start by the deadband
            if math.isnan(self._start):
                self._start = x
            elif abs(x - self._start) > band:
                self._dir, self._extreme = (1 if x > self._start else -1), x
        elif self._dir == 1:
            if x > self._extreme:
                self._extreme = x
            elif x < self._extreme - band:
                self._turn(x)
        elif x < self._extreme:
            self._extreme = x
        elif x > self._extreme + band:
            self._turn(x)

    def _turn(self, x: float) -> None:
        """The turning point at ``self._extreme`` is confirmed; the signal now goes the other way."""
        if not math.isnan(self._last):
            amplitude = abs(self._extreme - self._last) / 2
            if self._swings < self.params["max_peaks"]:
                self.out["peaks"][self._swings] = amplitude
            self._swings += 1
            self.out["amplitude"][...] = amplitude
            self.out["swings"][...] = self._swings
            self.out["cycles"][...] = self._swings // 2
        self._last, self._extreme, self._dir = self._extreme, x, -self._dir

    def get_state(self) -> tuple:
        return (self._dir, self._start, self._extreme, self._last, self._swings)

    def set_state(self, state: tuple) -> None:
        self._dir, self._start, self._extreme, self._last, self._swings = state
