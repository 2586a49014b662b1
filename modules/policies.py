"""Policies with a few parameters that a brain learns in its simulator.

`SwingPolicy` (the paper's swing learning, Fig. 19): pump a swing with the legs, the legs' offsets a
smooth function of the swing's state whose weights are run-time parameters, so an optimiser can try
one set of weights per branch of a batch (`Batch.run(..., params={"policy.w_angle": [...]})`)::

    drive = tanh(w_angle * angle + w_rate * rate + bias)
    hip   = hip_amplitude  * level        (rad)
    knee  = knee_amplitude * level        (rad)

where ``level`` follows ``drive`` at no more than ``speed`` rad/s of the larger amplitude: the same
legs, amplitudes and speed limit as the hand-written rule (`reflexes.PhasePump`), which is this
policy with ``w_angle = 0``, ``w_rate = 1 / rate_scale`` and ``bias = 0``. What the weights change is
when the legs move: a term in the angle moves them earlier or later than the sign of the rate says.

The outputs are offsets to connect to the servo's ``<joint>.q_ref`` inputs, as PhasePump's are.
"""

from __future__ import annotations

import math

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.module import Module, Param, Port


class SwingPolicy(Module):
    """Leg offsets for pumping a swing, from its angle and rate (see the module docstring).

    Inputs ``angle`` (rad) and ``rate`` (rad/s) of the swing's hinge (the core's ``<joint>.q`` and
    ``.qd``). Outputs ``hip`` and ``knee`` (rad). State: ``level`` (the smoothed drive, -1 to 1).
    """

    PARAMS = (
        Param("w_angle", 0.0, unit="1/rad", runtime=True, doc="weight of the swing angle"),
        Param("w_rate", 0.0, unit="s/rad", runtime=True, doc="weight of the swing rate"),
        Param("bias", 0.0, runtime=True, doc="constant added to the weighted sum"),
        Param("hip_amplitude", 0.6, unit="rad", dimension="angle", runtime=True, doc="hip pitch offset at drive 1"),
        Param("knee_amplitude", -0.6, unit="rad", dimension="angle", runtime=True, doc="knee offset at drive 1"),
        Param("speed", 2.0, unit="rad/s", runtime=True, doc="how fast the larger offset may change"),
    )

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        speed = self._param_values["speed"]
        if not speed > 0:
            raise DynabrainError(f"module {name!r} [params.speed]: must be positive, got {speed!r}")

    def inputs(self) -> list[Port]:
        return [Port("angle", (), "rad", "swing angle"), Port("rate", (), "rad/s", "swing angular rate")]

    def outputs(self) -> list[Port]:
        return [Port("hip", (), "rad"), Port("knee", (), "rad")]

    def start(self, t_ns: int) -> None:
        self._level = 0.0
        self.out["hip"][...] = 0.0
        self.out["knee"][...] = 0.0

    def step(self, t_ns: int, dt_ns: int) -> None:
        p = self._param_values
        drive = math.tanh(p["w_angle"] * float(self.inp["angle"]) + p["w_rate"] * float(self.inp["rate"]) + p["bias"])
        reach = p["speed"] * dt_ns * 1e-9 / max(abs(p["hip_amplitude"]), abs(p["knee_amplitude"]), 1e-9)
        self._level += min(max(drive - self._level, -reach), reach)
        self.out["hip"][...] = p["hip_amplitude"] * self._level
        self.out["knee"][...] = p["knee_amplitude"] * self._level

    def get_state(self) -> float:
        return self._level

    def set_state(self, state: float) -> None:
        self._level = state
