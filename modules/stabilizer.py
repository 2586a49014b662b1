"""A brain-side stabilizer (the paper's ``:stabilize-start``): the ankle strategy, from the ZMP sensor.

This is how a user writes a real-time action module: it reads sensor ports, keeps a little state,
and writes offsets that the servo adds to its targets, every period. Nothing in it knows the physics
core.

The law: the error ``e`` is the ZMP minus the centre of the support polygon, turned into the robot's
heading (x forward, y left), low-pass filtered (time constant ``filter``). The ankles turn the body
against it with a proportional-integral law (the integral keeps the body upright on a floor that
stays tilted):

    pitch = kp e_x + ki int(e_x),    roll = -(kp e_y + ki int(e_y)),    each clamped to +-max_angle

With the servo's conventions (a positive ankle pitch leans the body back over a flat foot, a
positive ankle roll leans it left) a ZMP ahead of the centre leans the body back, which brings the
centre of mass, and so the ZMP, back. The filter matters: to lean the body back the ankles first
push the toes down, which moves the ZMP *forward* for a moment (the ZMP is non-minimum-phase in the
ankle angle); fed back unfiltered, it rocks the robot off its feet. For an inverted pendulum of
height h on stiff ankles, the integral loop is stable when ``filter > ki h^2 / g`` (0.064 s for
h = 0.28 m and ``ki`` = 8); the defaults (``kp`` 0, ``ki`` 8 rad/(m*s), ``filter`` 0.2 s) suit a 60 cm
robot. When the ZMP is undefined (no foot loaded) the integral holds.

Ports: inputs ``zmp`` (3, m) and ``center`` (3, m) (connect the `ZmpSensor`'s); outputs ``pitch`` and
``roll`` (rad), to be connected to the servo's ``<ankle joint>.q_ref`` of both feet.
"""

from __future__ import annotations

import math

import numpy as np

from dynabrain.orchestrator.kernel.module import Module, Param, Port

from .mujoco.access import fail


class Stabilizer(Module):
    """Ankle strategy: PI control of the ZMP towards the centre of the support polygon."""

    PARAMS = (
        Param("kp", 0.0, unit="rad/m", runtime=True, doc="ankle angle per metre of ZMP error"),
        Param("ki", 8.0, unit="rad/(m*s)", runtime=True, doc="integral gain"),
        Param("max_angle", 0.35, unit="rad", dimension="angle", runtime=True, doc="limit of the ankle offsets"),
        Param("heading", 0.0, unit="rad", dimension="angle", runtime=True, doc="the robot's forward direction"),
        Param("filter", 0.2, unit="s", dimension="time", runtime=True,
              doc="time constant of the low-pass filter on the ZMP error"),
    )

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        for key in ("kp", "ki", "max_angle"):
            if not self.params[key] >= 0:
                raise fail(name, f"params.{key}", f"must be zero or positive, got {self.params[key]!r}")

    def inputs(self) -> list[Port]:
        return [Port("zmp", (3,), "m", "ZMP"), Port("center", (3,), "m", "centre of the support polygon")]

    def outputs(self) -> list[Port]:
        return [Port("pitch", (), "rad", "ankle pitch offset"), Port("roll", (), "rad", "ankle roll offset")]

    def start(self, t_ns: int) -> None:
        self._integral = (0.0, 0.0)
        self._error = (0.0, 0.0)
        self.out["pitch"][...] = 0.0
        self.out["roll"][...] = 0.0

    def step(self, t_ns: int, dt_ns: int) -> None:
        p = self.params
        zmp, center = self.inp["zmp"], self.inp["center"]
        ix, iy = self._integral
        ex, ey = self._error
        limit = p["max_angle"]
        if np.isfinite(zmp[0]) and np.isfinite(center[0]):
            dx, dy = float(zmp[0] - center[0]), float(zmp[1] - center[1])
            c, s = math.cos(p["heading"]), math.sin(p["heading"])
            dt = dt_ns * 1e-9
            a = dt / (p["filter"] + dt)
            ex += a * (c * dx + s * dy - ex)
            ey += a * (-s * dx + c * dy - ey)
            bound = limit / p["ki"] if p["ki"] > 0 else 0.0
            ix = min(max(ix + ex * dt, -bound), bound)
            iy = min(max(iy + ey * dt, -bound), bound)
            self._integral, self._error = (ix, iy), (ex, ey)
        pitch = p["kp"] * ex + p["ki"] * ix
        roll = -(p["kp"] * ey + p["ki"] * iy)
        self.out["pitch"][...] = min(max(pitch, -limit), limit)
        self.out["roll"][...] = min(max(roll, -limit), limit)

    def get_state(self) -> tuple:
        return (self._integral, self._error)

    def set_state(self, state: tuple) -> None:
        self._integral, self._error = state
