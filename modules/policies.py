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
from dynabrain.orchestrator.kernel.module import Param

from .reflexes import LegPump


class SwingPolicy(LegPump):
    """Leg offsets for pumping a swing, from its angle and rate (see the module docstring).

    Ports, speed limit and state as every `reflexes.LegPump` (the hand rule's too); only `drive` is its own.
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
        speed = self.params["speed"]
        if not speed > 0:
            raise DynabrainError(f"module {name!r} [params.speed]: must be positive, got {speed!r}")

    def drive(self, angle: float, rate: float) -> float:
        p = self.params
        return math.tanh(p["w_angle"] * angle + p["w_rate"] * rate + p["bias"])
