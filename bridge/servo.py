"""A joint-space PD servo: the small actuator module the bridge's examples, the robot emulator and the
tests drive (the robot modules proper come with the humanoid)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.module import Module, Param, Port, SetupContext
from dynabrain.orchestrator.kernel.suggest import did_you_mean


class PDServo(Module):
    """``force = clip(kp * (target - q) - kd * qd, -max_force, max_force)`` for the joints named in
    ``targets`` (hinges: rad, N*m; slides: m, N).

    Ports (block ports, with one view per joint ``<joint>.q`` ...):

    - inputs ``target`` (n,): the set points (unconnected, a brain sets it); ``q``, ``qd`` (n,): connect
      the core's ``joint_q`` / ``joint_qd`` (or each ``core.<joint>.q`` to ``servo.<joint>.q``);
    - output ``force`` (n,): connect to the core's ``joint_force`` (or per joint).

    The servo has no state: its force depends only on the inputs of the step (feedthrough), so the
    schedule steps it after the core's outputs are copied and before the core.
    """

    PARAMS = (
        Param("kp", 50.0, unit="N*m/rad", runtime=True, doc="proportional gain"),
        Param("kd", 2.0, unit="N*m*s/rad", runtime=True, doc="derivative gain"),
        Param("max_force", 100.0, unit="N*m", runtime=True, doc="saturation of each joint's force"),
        Param("unit", "rad", doc="unit of the joint positions: rad (hinges) or m (slides)"),
    )

    def __init__(self, name: str, *, targets: Sequence[str] = (), **params):
        super().__init__(name, targets=targets, **params)
        if not self.targets:
            raise DynabrainError(f"module {name!r} (PDServo): `targets` must name the joints it drives")
        if len(set(self.targets)) != len(self.targets):
            raise DynabrainError(f"module {name!r} (PDServo): a joint is named twice in targets {list(self.targets)}")
        for key in ("kp", "kd", "max_force"):
            self._check(key, self.params[key])

    @property
    def joints(self) -> tuple[str, ...]:
        return self.targets

    def _units(self) -> tuple[str, str, str]:
        unit = self.params["unit"]
        return unit, f"{unit}/s", "N*m" if unit == "rad" else "N"

    def inputs(self):
        uq, uqd, _ = self._units()
        n = len(self.targets)
        ports = [Port("target", (n,), uq, "set points"), Port("q", (n,), uq, "joint positions"),
                 Port("qd", (n,), uqd, "joint velocities")]
        for i, j in enumerate(self.targets):
            ports += [Port(f"{j}.target", (), uq, view_of=("target", i)), Port(f"{j}.q", (), uq, view_of=("q", i)),
                      Port(f"{j}.qd", (), uqd, view_of=("qd", i))]
        return tuple(ports)

    def outputs(self):
        uf = self._units()[2]
        ports = [Port("force", (len(self.targets),), uf, "joint forces")]
        ports += [Port(f"{j}.force", (), uf, view_of=("force", i)) for i, j in enumerate(self.targets)]
        return tuple(ports)

    def setup(self, ctx: SetupContext) -> None:
        if ctx.core is None:
            return
        known = ctx.core.joints()
        for joint in self.targets:
            if joint not in known:
                raise DynabrainError(f"module {self.name!r} (PDServo): no joint {joint!r} in the scene"
                                     + did_you_mean(joint, known))

    def bind(self) -> None:
        self._target, self._q, self._qd = self.inp["target"], self.inp["q"], self.inp["qd"]
        self._force = self.out["force"]

    def start(self, t_ns: int) -> None:
        self.out["force"][...] = 0.0

    def step(self, t_ns: int, dt_ns: int) -> None:
        p = self.params
        f = p["kp"] * (self._target - self._q) - p["kd"] * self._qd
        np.clip(f, -p["max_force"], p["max_force"], out=self._force)

    def set_param(self, name: str, value, *, running: bool = True) -> None:
        spec = self.param_specs().get(name)
        if spec is not None and name in ("kp", "kd", "max_force"):
            self._check(name, spec.convert(value))
        super().set_param(name, value, running=running)

    def _check(self, name: str, value: float) -> None:
        if not (np.isfinite(value) and value >= 0):
            raise DynabrainError(f"module {self.name!r} (PDServo): {name} must be a finite number >= 0, got {value!r}")
