"""Small signal modules: sources, gains, integrators, noise. Useful in scenarios, tests and benchmarks,
and as short examples of the module contract."""

from __future__ import annotations

import math

import numpy as np

from dynabrain.orchestrator.kernel.module import Capabilities, Module, Param, Port, SetupContext


class Constant(Module):
    """Outputs a constant vector ``value`` on port ``y`` (run-time settable)."""

    PARAMS = (Param("value", (0.0,), doc="the value", runtime=True), Param("unit", "1", doc="unit of y"))
    CAPABILITIES = Capabilities(feedthrough=False)

    def outputs(self):
        return (Port("y", (len(self.params["value"]),), self.params["unit"]),)

    def start(self, t_ns):
        self.out["y"][...] = self.params["value"]

    def step(self, t_ns, dt_ns):
        self.out["y"][...] = self.params["value"]


class Sine(Module):
    """``y = offset + amplitude * sin(2 pi f t + phase)``, evaluated at the end of each step."""

    PARAMS = (
        Param("amplitude", 1.0, runtime=True),
        Param("frequency", 1.0, unit="Hz", dimension="frequency", runtime=True),
        Param("phase", 0.0, unit="rad", dimension="angle"),
        Param("offset", 0.0, runtime=True),
        Param("unit", "1"),
    )
    CAPABILITIES = Capabilities(feedthrough=False)

    def outputs(self):
        return (Port("y", (), self.params["unit"]),)

    def _value(self, t_ns: int) -> float:
        p = self.params
        return p["offset"] + p["amplitude"] * math.sin(2 * math.pi * p["frequency"] * t_ns * 1e-9 + p["phase"])

    def start(self, t_ns):
        self.out["y"][...] = self._value(t_ns)

    def step(self, t_ns, dt_ns):
        self.out["y"][...] = self._value(t_ns + dt_ns)


class Gain(Module):
    """``y = k * u + offset`` for an ``n``-vector (``n`` 0: a scalar), direct feedthrough (an SSP's linear
    transformation on a connection is one)."""

    PARAMS = (Param("k", 1.0, runtime=True), Param("n", 1), Param("unit", "1"), Param("offset", 0.0, runtime=True))

    def _shape(self) -> tuple[int, ...]:
        return (self.params["n"],) if self.params["n"] else ()

    def inputs(self):
        return (Port("u", self._shape(), self.params["unit"]),)

    def outputs(self):
        return (Port("y", self._shape(), self.params["unit"]),)

    def step(self, t_ns, dt_ns):
        p = self.params
        np.multiply(self.inp["u"], p["k"], out=self.out["y"])
        if p["offset"]:
            self.out["y"] += p["offset"]


class Integrator(Module):
    """``x' = u``; output ``y = x`` (not feedthrough: a loop through an integrator is no algebraic loop)."""

    PARAMS = (Param("n", 1), Param("x0", 0.0))
    CAPABILITIES = Capabilities(feedthrough=False)

    def inputs(self):
        return (Port("u", (self.params["n"],)),)

    def outputs(self):
        return (Port("y", (self.params["n"],)),)

    def start(self, t_ns):
        self.x = np.full(self.params["n"], self.params["x0"])
        self.out["y"][...] = self.x

    def step(self, t_ns, dt_ns):
        self.x = self.x + self.inp["u"] * (dt_ns * 1e-9)
        self.out["y"][...] = self.x

    def get_state(self):
        return self.x.copy()

    def set_state(self, state):
        self.x = state.copy()
        self.out["y"][...] = self.x


class Noise(Module):
    """Gaussian noise ``y ~ N(0, sigma)`` from the module's own seeded generator (its state rolls back)."""

    PARAMS = (Param("n", 1), Param("sigma", 1.0, runtime=True), Param("unit", "1"))
    CAPABILITIES = Capabilities(feedthrough=False)

    def setup(self, ctx: SetupContext):
        self.rng = ctx.rng

    def outputs(self):
        return (Port("y", (self.params["n"],), self.params["unit"]),)

    def step(self, t_ns, dt_ns):
        self.out["y"][...] = self.rng.normal(0.0, self.params["sigma"], self.params["n"])

    def get_state(self):
        return self.rng.bit_generator.state

    def set_state(self, state):
        self.rng.bit_generator.state = state


class Counter(Module):
    """Counts its steps; output ``count``. The smallest module with state (tests, benchmarks)."""

    def outputs(self):
        return (Port("count", ()),)

    def start(self, t_ns):
        self.count = 0

    def step(self, t_ns, dt_ns):
        self.count += 1
        self.out["count"][...] = self.count

    def get_state(self):
        return self.count

    def set_state(self, state):
        self.count = state
