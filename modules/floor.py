"""The moving floor: a floor body driven along a slide and/or a tilt joint (the paper's earthquake module).

The floor is a body of the scene on a slide joint (horizontal motion) and/or a hinge (tilt), heavy,
with no motor of its own. This module makes it follow

    position(t) = e(t) A sin(phi(t)),   phi' = 2 pi f,     tilt_angle(t) = e(t) B sin(psi(t)),   psi' = 2 pi g

where the phases start at ``2 pi f t`` when the module joins (and integrate the frequencies after, so
a frequency changed at run time stays continuous) and the envelope ``e`` moves linearly, in ``ramp``
seconds, towards 1 while ``enabled`` and towards 0 when not; it starts at 0, so a floor that joins a
running world eases in. Each joint is driven by ``kp (x - q) + kd (v - qd) + mass * a`` (``tilt_kp``,
``tilt_kd``, ``inertia`` for the tilt), with ``v`` and ``a`` the exact derivatives of the reference.

A floor is meant to be added while the world runs (``add_module``; a scenario's ``add:`` event).
Until then nothing drives it: keep it frozen (out of the selection) and select it when the module
arrives; with ``targets: [floor]`` (the floor's object) the module checks that it is simulated.

Ports. The slide's are those of the FMU twin ``fmus/moving_floor`` (same names, units, parameters
and law; the twin has no tilt):

================  =====  ======  ==================================================================
port              dir    unit    meaning
================  =====  ======  ==================================================================
``q``             in     m       slide joint position (``core.<slide>.q``)
``qd``            in     m/s     slide joint velocity (``core.<slide>.qd``)
``position``      out    m       the slide's reference
``velocity``      out    m/s     its rate
``force``         out    N       force on the slide joint (``core.<slide>.force``)
``tilt_q``        in     rad     tilt joint angle (``core.<tilt>.q``)
``tilt_qd``       in     rad/s   tilt joint rate (``core.<tilt>.qd``)
``tilt_angle``    out    rad     the tilt's reference
``tilt_rate``     out    rad/s   its rate
``tilt_torque``   out    N*m     torque on the tilt joint (``core.<tilt>.force``)
================  =====  ======  ==================================================================

Parameters (run-time settable unless noted): ``amplitude`` (m), ``frequency`` (Hz), ``enabled``,
``ramp`` (s), ``kp`` (N/m), ``kd`` (N*s/m), ``mass`` (kg, what the slide moves); ``tilt_amplitude``
(rad, ``5deg`` works), ``tilt_frequency`` (Hz), ``tilt_kp`` (N*m/rad), ``tilt_kd`` (N*m*s/rad),
``inertia`` (kg*m^2, the plate about its tilt axis). The defaults suit the 80 kg floor of
``scenarios/models/earthquake.xml`` (a 60 rad/s tracking loop).
"""

from __future__ import annotations

import math
from typing import Any

from dynabrain.orchestrator.kernel.module import Module, Param, Port, SetupContext

from .mujoco.access import fail

TWO_PI = 2.0 * math.pi
_AXES = (("amplitude", "frequency", "kp", "kd", "mass"),  # the parameters of each axis: slide, then tilt
         ("tilt_amplitude", "tilt_frequency", "tilt_kp", "tilt_kd", "inertia"))


class MovingFloor(Module):
    """Drives a floor's slide and tilt joints along sinusoids (see the module docstring)."""

    PARAMS = (
        Param("amplitude", 0.0, unit="m", dimension="length", runtime=True, doc="slide amplitude"),
        Param("frequency", 0.5, unit="Hz", dimension="frequency", runtime=True, doc="slide frequency"),
        Param("enabled", True, runtime=True, doc="drive on (the envelope ramps to 1) or off (to 0)"),
        Param("ramp", 1.0, unit="s", dimension="time", runtime=True, doc="time for the envelope to go 0 <-> 1"),
        Param("kp", 288000.0, unit="N/m", runtime=True, doc="slide stiffness"),
        Param("kd", 9600.0, unit="N*s/m", runtime=True, doc="slide damping"),
        Param("mass", 80.0, unit="kg", dimension="mass", runtime=True, doc="mass moved by the slide (feedforward)"),
        Param("tilt_amplitude", 0.0, unit="rad", dimension="angle", runtime=True, doc="tilt amplitude"),
        Param("tilt_frequency", 0.5, unit="Hz", dimension="frequency", runtime=True, doc="tilt frequency"),
        Param("tilt_kp", 17300.0, unit="N*m/rad", runtime=True, doc="tilt stiffness"),
        Param("tilt_kd", 577.0, unit="N*m*s/rad", runtime=True, doc="tilt damping"),
        Param("inertia", 4.81, unit="kg*m^2", runtime=True, doc="moment of inertia of the plate (feedforward)"),
    )

    def __init__(self, name: str, **kwargs: Any):
        super().__init__(name, **kwargs)
        self._check(self.params)

    def _check(self, p: dict[str, Any]) -> None:
        for key in ("frequency", "tilt_frequency", "ramp", "kp", "kd", "mass", "tilt_kp", "tilt_kd", "inertia"):
            if not p[key] >= 0:
                raise fail(self.name, f"params.{key}", f"must be zero or positive, got {p[key]!r}")

    def set_param(self, name: str, value: Any, *, running: bool = True) -> None:
        spec = self.param_specs().get(name)
        if spec is not None:  # refuse a bad value before it becomes the parameter's value
            self._check({**self.params, name: spec.convert(value)})
        super().set_param(name, value, running=running)

    def inputs(self) -> list[Port]:
        return [Port("q", (), "m"), Port("qd", (), "m/s"), Port("tilt_q", (), "rad"), Port("tilt_qd", (), "rad/s")]

    def outputs(self) -> list[Port]:
        return [Port("position", (), "m"), Port("velocity", (), "m/s"), Port("force", (), "N"),
                Port("tilt_angle", (), "rad"), Port("tilt_rate", (), "rad/s"), Port("tilt_torque", (), "N*m")]

    def setup(self, ctx: SetupContext) -> None:
        if self.targets and ctx.core is not None:
            unknown = [o for o in self.targets if o not in ctx.core.objects()]
            if unknown:
                raise fail(self.name, "targets", f"{unknown[0]!r} is not an object of the scene "
                           f"(objects: {', '.join(ctx.core.objects())})")
            frozen = [o for o in self.targets if o not in ctx.core.selection]
            if frozen and not ctx.importing:  # (an imported state brings its own selection)
                raise fail(self.name, "targets", f"the floor {frozen[0]!r} is frozen (not selected): select it "
                           "(make) before the moving floor is added, or it will not move")

    def bind(self) -> None:
        self._law_of: dict[str, Any] | None = None

    def start(self, t_ns: int) -> None:
        p, t = self.params, t_ns * 1e-9
        self._state = (0.0, math.fmod(TWO_PI * p["frequency"] * t, TWO_PI),
                       math.fmod(TWO_PI * p["tilt_frequency"] * t, TWO_PI))
        self._drive(0.0)

    def step(self, t_ns: int, dt_ns: int) -> None:
        if self.params is not self._law_of:
            self._take_law()
        h = dt_ns * 1e-9
        envelope, phi, psi = self._state
        rate = self._envelope_rate(envelope)
        envelope = min(max(envelope + rate * h, 0.0), 1.0)
        (_, omega, *_), (_, tilt_omega, *_) = self._axes
        self._state = (envelope, math.fmod(phi + omega * h, TWO_PI), math.fmod(psi + tilt_omega * h, TWO_PI))
        self._drive(rate if self._envelope_rate(envelope) != 0.0 else 0.0)

    def _take_law(self) -> None:
        """Cache the law's constants for the current parameter dict (copy-on-write: a new dict is a
        change): the envelope's target and speed, and per axis (amplitude, 2 pi f, kp, kd, mass)."""
        p = self._law_of = self.params
        self._target = 1.0 if p["enabled"] else 0.0
        self._speed = 1.0 / p["ramp"] if p["ramp"] > 0 else math.inf
        self._axes = tuple((p[amp], TWO_PI * p[freq], p[kp], p[kd], p[inertia])
                           for amp, freq, kp, kd, inertia in _AXES)

    def _envelope_rate(self, envelope: float) -> float:
        target = self._target
        if envelope == target:
            return 0.0
        return self._speed if target > envelope else -self._speed

    def _drive(self, de: float) -> None:
        """References and drive forces from the state and the inputs (both axes)."""
        if self.params is not self._law_of:
            self._take_law()
        e, phi, psi = self._state
        (amp, omega, kp, kd, inertia), (t_amp, t_omega, t_kp, t_kd, t_inertia) = self._axes
        q, qd, tilt_q, tilt_qd = self.inp_flat.tolist()  # the inputs in the order `inputs` declares them
        x, v, acc = wave(amp, omega, phi, e, de)
        tx, tv, t_acc = wave(t_amp, t_omega, psi, e, de)
        self.out_flat[:] = (x, v, kp * (x - q) + kd * (v - qd) + inertia * acc,  # the outputs, in order
                            tx, tv, t_kp * (tx - tilt_q) + t_kd * (tv - tilt_qd) + t_inertia * t_acc)

    def get_state(self) -> tuple[float, float, float]:
        return self._state

    def set_state(self, state: tuple[float, float, float]) -> None:
        self._state = state


def wave(amplitude: float, omega: float, phase: float, envelope: float, envelope_rate: float
         ) -> tuple[float, float, float]:
    """Position, velocity and acceleration of ``e A sin(phase)`` with ``phase' = omega``, ``e' = envelope_rate``
    (and ``e'' = 0``)."""
    s, c = math.sin(phase), math.cos(phase)
    x = envelope * amplitude * s
    v = envelope_rate * amplitude * s + envelope * amplitude * omega * c
    a = 2.0 * envelope_rate * amplitude * omega * c - envelope * amplitude * omega * omega * s
    return x, v, a
