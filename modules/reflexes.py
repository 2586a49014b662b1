"""Sensor-based leg reflexes for the see-saw and the swing: brain-side rules as modules.

`ContactKick` (the paper's see-saw riders): when the foot's force sensor feels the ground, kick:
add ``hip_offset`` and ``knee_offset`` to the servo's targets for ``duration``, then rest for ``rest``
(the rule ignores the sensor meanwhile), then wait for the next contact.

`PhasePump` (the paper's swing): pump with the legs on a phase rule: the legs go one way while the
swing moves forward and the other way while it moves back, ``offset = amplitude * tanh(rate /
rate_scale)`` (a smooth sign) for the hips and the knees, changing no faster than ``speed``: legs
that jumped at every sign change would shake the swing at their own pace instead of pumping it.

Both write offsets in rad, to be connected to the servo's ``<joint>.q_ref`` inputs (one output may
drive the joints of both legs).
"""

from __future__ import annotations

import math

import numpy as np

from dynabrain.orchestrator.kernel.module import Module, Param, Port

from .mujoco.access import fail


class ContactKick(Module):
    """Kick when the foot touches: a three-state rule (ready, kicking, resting) on a force sensor.

    Input ``force`` (3, N): a foot force sensor's ``force``; contact is ``|force| >= threshold``.
    Outputs ``hip``, ``knee`` (rad): the offsets, zero unless kicking; ``kicks`` (1): kicks so far.
    """

    PARAMS = (
        Param("threshold", 5.0, unit="N", runtime=True, doc="force that means the foot is on the ground"),
        Param("hip_offset", 0.8, unit="rad", dimension="angle", runtime=True, doc="hip pitch offset while kicking"),
        Param("knee_offset", -1.2, unit="rad", dimension="angle", runtime=True, doc="knee offset while kicking"),
        Param("duration", 0.25, unit="s", dimension="time", doc="how long a kick lasts"),
        Param("rest", 0.4, unit="s", dimension="time", doc="time after a kick during which contact is ignored"),
    )

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        for key in ("duration", "rest", "threshold"):
            if not self.params[key] > 0:
                raise fail(name, f"params.{key}", f"must be positive, got {self.params[key]!r}")

    def inputs(self) -> list[Port]:
        return [Port("force", (3,), "N", "foot force sensor")]

    def outputs(self) -> list[Port]:
        return [Port("hip", (), "rad"), Port("knee", (), "rad"), Port("kicks", (), "1")]

    def start(self, t_ns: int) -> None:
        self._mode, self._until, self._kicks = "ready", t_ns, 0
        self._write(False)

    def step(self, t_ns: int, dt_ns: int) -> None:
        p = self.params
        now = t_ns + dt_ns
        if self._mode == "ready" and float(np.linalg.norm(self.inp["force"])) >= p["threshold"]:
            self._mode, self._until, self._kicks = "kicking", now + round(p["duration"] * 1e9), self._kicks + 1
        elif self._mode == "kicking" and now >= self._until:
            self._mode, self._until = "resting", now + round(p["rest"] * 1e9)
        elif self._mode == "resting" and now >= self._until:
            self._mode = "ready"
        self._write(self._mode == "kicking")

    def _write(self, kicking: bool) -> None:
        p = self.params
        self.out["hip"][...] = p["hip_offset"] if kicking else 0.0
        self.out["knee"][...] = p["knee_offset"] if kicking else 0.0
        self.out["kicks"][...] = self._kicks

    def get_state(self) -> tuple:
        return (self._mode, self._until, self._kicks)

    def set_state(self, state: tuple) -> None:
        self._mode, self._until, self._kicks = state


class LegPump(Module):
    """Pump a swing with the legs: hip and knee offsets ``*_amplitude * level``, where ``level`` follows
    `drive` (from -1 to 1) at no more than ``speed`` rad/s of the larger amplitude.

    Inputs ``angle`` (rad) and ``rate`` (rad/s) of the swing's hinge (the core's ``<joint>.q`` and
    ``.qd``). Outputs ``hip`` and ``knee`` (rad), offsets for the servo's ``<joint>.q_ref`` inputs.
    State: ``level``. A subclass says what the legs aim for (`drive`) and declares the parameters
    ``hip_amplitude``, ``knee_amplitude`` and ``speed`` among its own.
    """

    def drive(self, angle: float, rate: float) -> float:
        """Where the legs aim, from -1 to 1, given the swing's angle and rate."""
        raise NotImplementedError

    def inputs(self) -> list[Port]:
        return [Port("angle", (), "rad", "swing angle"), Port("rate", (), "rad/s", "swing angular rate")]

    def outputs(self) -> list[Port]:
        return [Port("hip", (), "rad"), Port("knee", (), "rad")]

    def start(self, t_ns: int) -> None:
        self._level = 0.0
        self.out["hip"][...] = 0.0
        self.out["knee"][...] = 0.0

    def step(self, t_ns: int, dt_ns: int) -> None:
        p = self.params
        goal = self.drive(float(self.inp["angle"]), float(self.inp["rate"]))
        reach = p["speed"] * dt_ns * 1e-9 / max(abs(p["hip_amplitude"]), abs(p["knee_amplitude"]), 1e-9)
        self._level += min(max(goal - self._level, -reach), reach)
        self.out["hip"][...] = p["hip_amplitude"] * self._level
        self.out["knee"][...] = p["knee_amplitude"] * self._level

    def get_state(self) -> float:
        return self._level

    def set_state(self, state: float) -> None:
        self._level = state


class PhasePump(LegPump):
    """The hand-written rule: the legs follow the sign of the swing's angular rate, ``drive =
    tanh(rate / rate_scale)`` (see `LegPump` for the ports and the speed limit)."""

    PARAMS = (
        Param("hip_amplitude", 0.6, unit="rad", dimension="angle", runtime=True, doc="hip pitch amplitude"),
        Param("knee_amplitude", -0.6, unit="rad", dimension="angle", runtime=True, doc="knee amplitude"),
        Param("rate_scale", 0.1, unit="rad/s", runtime=True, doc="rate at which the legs are two thirds out"),
        Param("speed", 2.0, unit="rad/s", runtime=True, doc="how fast the offsets may change"),
    )

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        if not self.params["rate_scale"] > 0:
            raise fail(name, "params.rate_scale", "must be positive")

    def drive(self, angle: float, rate: float) -> float:
        return math.tanh(rate / self.params["rate_scale"])
