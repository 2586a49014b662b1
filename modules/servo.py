"""The servo: angle-vector targets to joint torques (PD with torque limits), after the paper's servo module.

The servo plays a motion program (a start ``pose`` and a timed ``sequence`` of angle-vectors, see
`modules.motion`) and adds the ``q_ref`` input to it: the target of joint i is
``program_i(t) + q_ref_i`` (with no program, ``q_ref`` is the target). Its command is
``clip(kp (target - q) + kd (target_rate - qd), +-tau_max)`` (the target rate is the program's;
``q_ref`` adds none), computed from the inputs at the start of the step and held over it; with
``lag`` > 0 the motor torque follows the command with a first-order lag of that time constant,
integrated exactly over each step.

Ports (n = number of joints; units for hinge joints, m and N for slide joints, "1" when mixed):

==========  ========  ======  =========================================================================
port        shape     unit    meaning
==========  ========  ======  =========================================================================
``q``       in (n,)   rad     joint positions (connect `Encoders` ``q``)
``qd``      in (n,)   rad/s   joint velocities (connect `Encoders` ``qd``)
``q_ref``   in (n,)   rad     target angles, added to the program's (a brain, a stabilizer, a rule)
``tau``     out (n,)  N*m     joint torques (for ``core.<joint>.force``)
``ctrl``    out (n,)  1       the same torques for the core's motors (``core.ctrl``): MuJoCo's actuator
                              controls carry no unit on the core; with ``gear="1"`` motors they are torques
``target``  out (n,)  rad     the target the last step used (program + q_ref)
==========  ========  ======  =========================================================================

Every vector port also has one port per element, a view into it: ``<joint>.q_ref``, ``<joint>.tau``
(by joint name) and ``q[1]`` ... ``q[n]``, ``qd[i]``, ``q_ref[i]``, ``tau[i]`` (1-based, as the FMU
adapter names the elements of an FMU's array variables). Drive a vector or its elements, not both.

Parameters: ``kp`` (N*m/rad), ``kd`` (N*m*s/rad), ``tau_max`` (N*m), ``lag`` (s) (all run-time
settable), ``pose`` (start angle-vector, default all zeros), ``sequence`` (run-time settable: a new
sequence starts from the current target at the next step), ``loop``, ``interpolation``
(``minjerk`` or ``linear``). Targets: joint names or glob patterns (default: every joint with a
motor, in the core's actuator order, so that ``ctrl`` fits ``core.ctrl``).

FMU twin (``fmus/servo``): the same ports ``q``, ``qd``, ``q_ref``, ``tau`` (and elements ``q[i]``...)
with the same units, and the same parameters ``kp``, ``kd``, ``tau_max``, ``lag`` and law (its
damping acts on ``-qd``: the same as here while no program moves the target). It has no motion
program, so a scenario that swaps it in gives its poses through ``q_ref``; its size is fixed when it
is built (``defines: {N: ...}``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.module import Module, Param, Port, SetupContext

from .motion import INTERPOLATIONS, Motion, MotionError, parse_motion, parse_pose
from .mujoco.access import MujocoLink, fail

_add, _subtract, _multiply, _minimum, _maximum = np.add, np.subtract, np.multiply, np.minimum, np.maximum


_PROGRAMS: dict[int, tuple[Motion, tuple]] = {}  # id of a program -> (it, what it is made of): `_program_key`


def _program_key(motion: Motion) -> tuple:
    """What a program is made of (its times, poses, loop, interpolation): equal keys play the same
    values at the same time, so branches whose programs are equal copies (a fork's, an imported state's)
    evaluate one. Kept per program object (held, so its id stays its own), made once."""
    hit = _PROGRAMS.get(id(motion))
    if hit is None or hit[0] is not motion:
        if len(_PROGRAMS) >= 4096:
            _PROGRAMS.clear()
        hit = _PROGRAMS[id(motion)] = (motion, (motion.times, motion.poses.tobytes(), motion.loop, motion.smooth))
    return hit[1]


class Servo(Module):
    """PD servos with torque limits for a set of joints, playing an angle-vector program."""

    PARAMS = (
        Param("kp", 40.0, unit="N*m/rad", runtime=True, doc="stiffness"),
        Param("kd", 1.5, unit="N*m*s/rad", runtime=True, doc="damping"),
        Param("tau_max", 4.0, unit="N*m", runtime=True, doc="torque limit (symmetric)"),
        Param("lag", 0.0, unit="s", dimension="time", runtime=True, doc="motor time constant (0: none)"),
        Param("pose", None, doc="start angle-vector (list or {joint: angle}); degrees unless a unit is given"),
        Param("sequence", None, runtime=True, doc="timed angle-vectors: [{pose: ..., duration: 0.5s}, ...]"),
        Param("loop", False, doc="repeat the sequence"),
        Param("interpolation", "minjerk", doc=f"one of {', '.join(INTERPOLATIONS)}"),
    )

    def __init__(self, name: str, **kwargs: Any):
        super().__init__(name, **kwargs)
        explicit = all(not any(ch in t for ch in "*?[") for t in self.targets)
        self._joints: list[str] = list(self.targets) if explicit else []
        self._slides = [False] * len(self._joints)
        self._check_gains(self.params)
        self._motion: Motion | None = None
        if self._joints:  # joints known now: check the program at construction
            self._motion = self._parse(self.params)

    @property
    def joints(self) -> list[str]:
        """The servo's joints, in the order of its vectors."""
        return list(self._joints)

    @property
    def slides(self) -> list[bool]:
        """Which of `joints` are slide joints (their values in m, the others in rad)."""
        return list(self._slides)

    @property
    def program(self) -> Motion | None:
        """The motion program the servo plays now (None before `setup`): a new object each time a sequence
        begins, which is how a robot link sees that one did (`program_start_ns` says when)."""
        return self._motion

    @property
    def program_start_ns(self) -> int:
        """The simulated time at which `program` began (the start of the step that began it)."""
        return self._t0

    # -- declarations -----------------------------------------------------------------------------------
    def _units(self) -> tuple[str, str, str]:
        if self._slides and all(self._slides):
            return "m", "m/s", "N"
        if any(self._slides):
            return "1", "1", "1"
        return "rad", "rad/s", "N*m"

    def inputs(self) -> list[Port]:
        n, (uq, uqd, _) = len(self._joints), self._units()
        ports = [Port("q", (n,), uq, "joint positions"), Port("qd", (n,), uqd, "joint velocities"),
                 Port("q_ref", (n,), uq, "target angles, added to the program's")]
        return ports + self._elements(("q", uq), ("qd", uqd), ("q_ref", uq)) + [
            Port(f"{j}.q_ref", (), uq, view_of=("q_ref", i)) for i, j in enumerate(self._joints)]

    def outputs(self) -> list[Port]:
        n, (uq, _, ut) = len(self._joints), self._units()
        ports = [Port("tau", (n,), ut, "joint torques"), Port("ctrl", (n,), "1", "the torques, for core.ctrl"),
                 Port("target", (n,), uq, "target angle-vector")]
        return ports + self._elements(("tau", ut)) + [
            Port(f"{j}.tau", (), ut, view_of=("tau", i)) for i, j in enumerate(self._joints)]

    def _elements(self, *vectors: tuple[str, str]) -> list[Port]:
        """Element views ``name[1]`` ... ``name[n]`` of vector ports (the FMU adapter's names)."""
        return [Port(f"{name}[{i + 1}]", (), unit, view_of=(name, i))
                for name, unit in vectors for i in range(len(self._joints))]

    # -- lifecycle ----------------------------------------------------------------------------------------
    def setup(self, ctx: SetupContext) -> None:
        if ctx.core is not None:
            link = MujocoLink(self.name, ctx.core)
            self._joints = link.expand_joints(self.targets)
            m = link.model
            slide = int(mujoco.mjtJoint.mjJNT_SLIDE)
            self._slides = [int(m.jnt_type[link.lookup("joint", j)]) == slide for j in self._joints]
        elif not self._joints:
            raise fail(self.name, "targets", "without a physics core the servo needs its joints named in targets")
        self._motion = self._parse(self.params)
        self._pending: Motion | None = None

    def bind(self) -> None:
        self._q, self._qd, self._ref = self.inp["q"], self.inp["qd"], self.inp["q_ref"]
        self._tau, self._ctrl, self._target = self.out["tau"], self.out["ctrl"], self.out["target"]
        n = len(self._joints)
        self._damp, self._cmd = np.zeros(n), np.zeros(n)
        self._gains_of: dict[str, Any] | None = None

    def start(self, t_ns: int) -> None:
        self._t0 = t_ns
        pos, _ = self._motion.at(0)
        self._target[...] = pos + self._ref
        self._tau[...] = 0.0
        self._ctrl[...] = 0.0

    def step(self, t_ns: int, dt_ns: int) -> None:
        if self._pending is not None:
            self._begin(t_ns)
        pos, rate = self._motion.at(t_ns - self._t0)
        if self.params is not self._gains_of:
            self._take_gains()
        kp, kd, high, low, lag = self._gains
        damp, target = self._damp, self._target
        cmd = self._cmd if lag > 0 else self._tau  # without lag the command is the torque
        _add(pos, self._ref, out=target)
        _subtract(target, self._q, out=cmd)
        _multiply(cmd, kp, out=cmd)
        _subtract(rate, self._qd, out=damp)
        _multiply(damp, kd, out=damp)
        _add(cmd, damp, out=cmd)
        _minimum(cmd, high, out=cmd)
        _maximum(cmd, low, out=cmd)
        if lag > 0:  # the motor follows the command: exact for a command held over the step
            cmd -= self._tau
            cmd *= -math.expm1(-dt_ns * 1e-9 / lag)
            self._tau += cmd
        self._ctrl[...] = self._tau

    @classmethod
    def step_batch(cls, members: Sequence[Module], t_ns: int, dt_ns: int, inp: np.ndarray, out: np.ndarray,
                   failed: dict[int, BaseException]) -> np.ndarray:
        """The servos of N branches in one go (`Module.step_batch`): each one's `step`, the same numpy
        operations over a leading branch axis (elementwise, so each row has the bits of its own step).
        Programs, gains and lags may differ per branch (a branch's parameters); the program is evaluated
        once per distinct (program, start)."""
        servos: list[Servo] = list(members)  # type: ignore[arg-type]
        n = len(servos[0]._joints)
        q, qd, ref = inp[:, :n], inp[:, n:2 * n], inp[:, 2 * n:3 * n]
        programs: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        keys = []
        gains_of = servos[0].params
        same_gains = True
        for servo in servos:  # one pass: what each servo's step checks first, and its program's key
            if servo._pending is not None:
                servo._begin(t_ns)
            params = servo.params
            if params is not servo._gains_of:
                servo._take_gains()
            same_gains = same_gains and params is gains_of
            motion = servo._motion
            key = servo._key if servo._key_of is motion else servo._program_key()
            keys.append((key, servo._t0))
        for servo, key in zip(servos, keys, strict=True):
            if key not in programs:
                programs[key] = servo._motion.at(t_ns - servo._t0)
        first = servos[0]
        pos, rate = next(iter(programs.values())) if len(programs) == 1 else (
            np.stack([programs[key][i] for key in keys]) for i in (0, 1))
        kp, kd, high, low = first._gains[:4] if same_gains else (
            np.stack([s._gains[i] for s in servos]) for i in range(4))
        new = np.empty(out.shape)
        tau, target = new[:, :n], new[:, 2 * n:3 * n]
        _add(pos, ref, out=target)
        _subtract(target, q, out=tau)
        _multiply(tau, kp, out=tau)
        damp = _subtract(rate, qd)
        _multiply(damp, kd, out=damp)
        _add(tau, damp, out=tau)
        _minimum(tau, high, out=tau)
        _maximum(tau, low, out=tau)
        lags = [s._gains[4] for s in servos]
        if any(lag > 0 for lag in lags):  # the motor follows the command (per branch: its own lag)
            rows = np.flatnonzero(np.array(lags) > 0)
            previous = out[rows, :n]
            cmd = tau[rows] - previous
            cmd *= np.array([-math.expm1(-dt_ns * 1e-9 / lags[r]) for r in rows])[:, None]
            tau[rows] = previous + cmd
        new[:, n:2 * n] = tau
        return new

    _key_of: Motion | None = None  # the program `_key` is the key of (`_program_key`)
    _key: tuple = ()

    def _program_key(self) -> tuple:
        self._key, self._key_of = _program_key(self._motion), self._motion
        return self._key

    def _take_gains(self) -> None:
        """Cache the gains of the current parameter dict (copy-on-write: a new dict is a change), as
        vectors: a ufunc of two arrays costs less than one of an array and a Python float, and gives
        the same bits."""
        p = self._gains_of = self.params
        n = len(self._joints)
        self._gains = (np.full(n, p["kp"]), np.full(n, p["kd"]), np.full(n, p["tau_max"]), np.full(n, -p["tau_max"]),
                       p["lag"])

    def _begin(self, t_ns: int) -> None:
        """Start the pending sequence now, from the current program target."""
        here, _ = self._motion.at(t_ns - self._t0)
        p = self.params
        self._motion = parse_motion(here, p["sequence"], self._joints, self._slides, loop=p["loop"],
                                    interpolation=p["interpolation"])
        self._t0 = t_ns
        self._pending = None

    def get_state(self) -> tuple:
        return (self._t0, self._motion, self._pending)

    def set_state(self, state: tuple) -> None:
        self._t0, self._motion, self._pending = state

    def steps_change_state(self) -> bool:
        return self._pending is not None  # a new program starts at the next step

    # -- parameters ---------------------------------------------------------------------------------------
    def set_param(self, name: str, value: Any, *, running: bool = True) -> None:
        spec = self.param_specs().get(name)
        if spec is not None:  # refuse a bad value before it becomes the parameter's value
            trial = dict(self.params)
            trial[name] = spec.convert(value)
            self._check_gains(trial)
            if name == "sequence" and self._joints:
                self._parse(trial)
        super().set_param(name, value, running=running)

    def on_param(self, name: str, value: Any) -> None:
        if name == "sequence" and hasattr(self, "_pending"):
            self._pending = self._motion  # marks a restart; `_begin` parses the new sequence

    def _check_gains(self, p: dict[str, Any]) -> None:
        for key in ("kp", "kd", "tau_max", "lag"):
            if not p[key] >= 0:
                raise fail(self.name, f"params.{key}", f"must be zero or positive, got {p[key]!r}")

    def _parse(self, p: dict[str, Any]) -> Motion:
        try:
            base = np.zeros(len(self._joints))
            start = base if p["pose"] is None else parse_pose(p["pose"], self._joints, self._slides, base, "pose")
            return parse_motion(start, p["sequence"], self._joints, self._slides, loop=p["loop"],
                                interpolation=p["interpolation"])
        except MotionError as exc:
            raise fail(self.name, f"params.{exc.field}", str(exc)) from None
