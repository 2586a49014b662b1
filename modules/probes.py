"""Probes: modules that measure something about the run for expectations (no effect on physics)."""

from __future__ import annotations

import numpy as np

from dynabrain.orchestrator.kernel.module import Capabilities, Module, Param, Port


class BounceMeter(Module):
    """Apex heights of a bouncing body, from its position.

    Input ``pos`` (3, m): connect the body's ``core.<body>.pos``. Output ``apexes`` (``max_apexes``,
    m): the heights above ``floor`` of the body's bottom at each apex of its flight, the first being
    the height it starts falling from, NaN until reached; ``count``: apexes recorded so far. Apexes
    lower than ``min_height`` (contact jitter at rest) are ignored.
    """

    CAPABILITIES = Capabilities(finite_outputs=False)  # NaN: an apex not reached yet

    PARAMS = (
        Param("radius", 0.0, unit="m", dimension="length", doc="distance from the body origin to its bottom"),
        Param("floor", 0.0, unit="m", dimension="length", doc="height of the surface it bounces on"),
        Param("min_height", 0.01, unit="m", dimension="length", doc="lower apexes are ignored"),
        Param("max_apexes", 12, doc="how many apexes are kept"),
    )

    def inputs(self):
        return (Port("pos", (3,), "m", "position of the body"),)

    def outputs(self):
        return (Port("apexes", (self.params["max_apexes"],), "m", "apex heights, NaN until reached"),
                Port("count", (), "1", "apexes recorded"))

    def start(self, t_ns):
        self._prev: float | None = None
        self._rising = True
        self._count = 0
        self.out["apexes"][...] = np.nan
        self.out["count"][...] = 0

    def step(self, t_ns, dt_ns):
        z = float(self.inp["pos"][2])
        prev = self._prev
        if prev is not None:
            if z > prev:
                self._rising = True
            elif z < prev and self._rising:
                self._rising = False
                height = prev - self.params["radius"] - self.params["floor"]
                if height >= self.params["min_height"] and self._count < self.params["max_apexes"]:
                    self.out["apexes"][self._count] = height
                    self._count += 1
                    self.out["count"][...] = self._count
        self._prev = z

    def get_state(self):
        return (self._prev, self._rising, self._count)

    def set_state(self, state):
        self._prev, self._rising, self._count = state
