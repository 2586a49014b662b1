"""Inverse kinematics for motion programs: end-effector targets to the servo's angle-vectors.

A brain says where a frame of the robot should be (a site, body or geom: a hand's tip at a point, a
tool pointing down, both feet kept where they are) and gets the joint angles that put it there, in the
servo's joint order and in the motion program's convention (`modules.motion`), ready for the servo's
``pose`` or ``sequence``. Solved by `mink` (differential inverse kinematics on MuJoCo: a quadratic
program per iteration, joint limits kept), not by a solver of our own.

    ik = InverseKinematics.for_servo(world, "servo")           # the servo's joints, the world's core
    above = ik.solve([Target("tip", pos=[0.43, 0, 0.45], axis=[0, 0, 1], direction=[0, 0, -1])])
    if above.reached:
        world.set("servo.sequence", [above.step("1s")])
    else:
        print(above.message)                                    # out of reach: how far the best pose is

Several targets at once solve for the whole body (each frame its target, weighted alike). Only the
chosen joints move; every other degree of freedom of the model (a free base, the drawer, other
robots) is held where it is, as the servo cannot move it. Joint ranges are kept.

The model is read through the MuJoCo core's public read-only view (`MujocoCore.mj`): the model the
core simulates now (a structural edit switches it; the solver follows) and, as the start of the
search, the joints' current positions. Nothing of the core is written: mink works on a copy of the
positions in its own `MjData`. While the world runs in its thread, solve under ``world.lock``.

A target out of reach is not an error: the result says ``reached=False``, with the best pose found
(the one closest to the targets in the weighted sense below) and how far each frame stayed from its
target. Bad input (an unknown frame or joint, a position that is not 3 finite numbers, a zero axis)
raises `IkError`, naming the call and the field.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import mink
import mujoco
import numpy as np
import qpsolvers

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.suggest import did_you_mean

from .mujoco.access import MujocoLink
from .servo import Servo

KINDS = ("site", "body", "geom")
ORIENTATION_COST = 0.2
"""Weight of an orientation error (per rad) against a position error (per m): a frame 1 cm off weighs
as much as one 0.05 rad (3 degrees) off."""
MAX_STEP = {"hinge": 0.2, "slide": 0.05}
"""How far one iteration may move a joint (rad, m): a far target is approached in steps, not in one
leap of the linearised problem that would overshoot it."""
LM_DAMPING = 1.0
"""mink's Levenberg-Marquardt damping of each task, scaled by its squared error: short steps while far."""
POLISH = 0.01
"""The search goes on past the tolerances, down to this fraction of them (it costs a few iterations)."""
STALL = 10
"""Iterations without getting closer after which the search stops (the best pose is where it cannot go on)."""
SOLVER = "daqp"
"""The QP solver mink calls (installed with mink)."""
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)


class IkError(DynabrainError):
    """A target or a joint set the solver cannot take; the message names the call and the field."""


def _fail(call: str, field: str, message: str) -> IkError:
    return IkError(f"{call} [{field}]: {message}")


@dataclass(frozen=True)
class Target:
    """Where a frame of the model should be, in the world frame.

    ``pos`` (m) places the frame's origin; ``quat`` (w, x, y, z) sets its whole orientation; ``axis`` and
    ``direction`` together point one axis of the frame (in the frame's coordinates) along a world
    direction, leaving the roll about it free (a finger pointing down, whatever its heading). Give a
    position, an orientation, or both. ``kind`` says what ``frame`` names: a site, a body or a geom.
    """

    frame: str
    pos: Sequence[float] | np.ndarray | None = None
    quat: Sequence[float] | np.ndarray | None = None
    axis: Sequence[float] | np.ndarray | None = None
    direction: Sequence[float] | np.ndarray | None = None
    kind: str = "site"


@dataclass(frozen=True)
class FrameError:
    """How far one frame stayed from its target: ``position_m`` (m), ``orientation_rad`` (rad, the
    angle between the orientations, or between the axis and the direction); 0 for what was not asked."""

    frame: str
    position_m: float
    orientation_rad: float


@dataclass(frozen=True)
class IkResult:
    """The best pose found for some targets (see the module docstring).

    ``q``: the joints' values in SI (rad, m), in the order of ``joints`` (the servo's when made with
    `InverseKinematics.for_servo`); ``reached``: every frame within the tolerances; ``errors``: per
    target; ``message``: a sentence saying what was reached, or how far from it the best pose is.
    """

    reached: bool
    q: np.ndarray
    joints: tuple[str, ...]
    slides: tuple[bool, ...]
    errors: tuple[FrameError, ...]
    iterations: int
    message: str
    q_full: np.ndarray | None = None
    """The whole configuration of the pose (the model's ``qpos``: a free base, every other joint as it was
    held); ``solve(start=result)`` starts the next search from it, to chain poses."""

    @property
    def position_error_m(self) -> float:
        """The largest position error over the targets (m)."""
        return max((e.position_m for e in self.errors), default=0.0)

    @property
    def orientation_error_rad(self) -> float:
        """The largest orientation error over the targets (rad)."""
        return max((e.orientation_rad for e in self.errors), default=0.0)

    def pose(self) -> dict[str, float]:
        """The pose as a motion program writes it: ``{joint: value}``, degrees for a hinge, metres for a
        slide (`modules.motion`); the servo's ``pose`` or a sequence step's ``pose`` takes it."""
        return {j: (float(v) if slide else math.degrees(float(v)))
                for j, v, slide in zip(self.joints, self.q, self.slides, strict=True)}

    def step(self, duration: str | float) -> dict[str, Any]:
        """One step of a servo ``sequence``: move to this pose in ``duration`` (``"0.5s"``, or seconds)."""
        return {"pose": self.pose(), "duration": duration if isinstance(duration, str) else f"{duration}s"}


class _ActiveLimit(mink.Limit):
    """mink's joint-range limit on the joints that move only: a held joint outside its range (a drawer
    pushed a little past its stop) must not make the problem infeasible."""

    def __init__(self, model: mujoco.MjModel, active_dofs: np.ndarray):
        self._limit = mink.ConfigurationLimit(model)
        self._mask = np.zeros(model.nv, dtype=bool)
        self._mask[active_dofs] = True

    def compute_qp_inequalities(self, configuration: mink.Configuration, dt: float) -> mink.Constraint:
        full = self._limit.compute_qp_inequalities(configuration, dt)
        if full.inactive:
            return full
        keep = np.any(full.G[:, self._mask] != 0, axis=1) & ~np.any(full.G[:, ~self._mask] != 0, axis=1)
        if not keep.any():
            return mink.Constraint()
        return mink.Constraint(G=full.G[keep], h=full.h[keep])


@dataclass
class _Problem:
    """What one compiled model needs: its view, the joints' addresses, the held degrees of freedom."""

    view: Any
    qpos_adr: np.ndarray
    dof_adr: np.ndarray
    limits: list
    constraints: list


class InverseKinematics:
    """Targets for frames of a MuJoCo model to values of some of its joints (see the module docstring).

    ``core``: the world's MuJoCo core (``world.core``); ``joints``: hinge and slide joints by name or
    glob pattern (empty: every joint with a motor, in actuator order, as the servo takes them).
    """

    CALL = "InverseKinematics"

    def __init__(self, core: Any, joints: Sequence[str] = ()):
        if isinstance(joints, str):
            joints = [joints]
        self._link = MujocoLink(self.CALL, core, field="joints")
        try:
            self.joints: tuple[str, ...] = tuple(self._link.expand_joints(list(joints)))
        except DynabrainError as exc:
            raise _fail(self.CALL, "joints", str(exc).split("]: ", 1)[-1]) from None
        m = self._link.model
        self.slides: tuple[bool, ...] = tuple(int(m.jnt_type[self._link.lookup("joint", j)]) == _SLIDE
                                              for j in self.joints)
        self._problem: _Problem | None = None

    @classmethod
    def for_servo(cls, world: Any, servo: str = "servo") -> InverseKinematics:
        """A solver for the joints of the world's servo module ``servo``, in its order."""
        module = world.modules.get(servo)
        if not isinstance(module, Servo):
            known = [n for n, m in world.modules.items() if isinstance(m, Servo)]
            raise _fail(f"{cls.CALL}.for_servo", "servo", f"no servo module {servo!r} in the world"
                        + did_you_mean(servo, known) + f"; servos: {', '.join(known) or 'none'}")
        return cls(world.core, module.joints)

    # -- reading the model --------------------------------------------------------------------------------
    def _current(self) -> _Problem:
        view = self._link.core.mj
        if self._problem is not None and self._problem.view is view:
            return self._problem
        m = view.model
        ids = []
        for j in self.joints:
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)
            if jid < 0:
                raise _fail(self.CALL, "joints", f"joint {j!r} is not in the core's current model (frozen?)")
            ids.append(jid)
        qpos_adr = np.array([m.jnt_qposadr[j] for j in ids], dtype=np.intp)
        dof_adr = np.array([m.jnt_dofadr[j] for j in ids], dtype=np.intp)
        free = {int(d) for d in self._free_dofs(m)}
        held = sorted(set(range(m.nv)) - {int(d) for d in dof_adr} - free)
        constraints = [mink.DofFreezingTask(m, dof_indices=held)] if held else []
        steps = mink.VelocityLimit(m, {j: MAX_STEP["slide" if s else "hinge"]
                                       for j, s in zip(self.joints, self.slides, strict=True)})
        active = np.array(sorted({int(d) for d in dof_adr} | free), dtype=np.intp)
        self._problem = _Problem(view, qpos_adr, dof_adr, [_ActiveLimit(m, active), steps], constraints)
        return self._problem

    def _free_dofs(self, m: mujoco.MjModel) -> np.ndarray:
        """Degrees of freedom besides the chosen joints that the solver may move (none: the whole-body
        solver frees the robot's floating base)."""
        return np.zeros(0, dtype=np.intp)

    def _support(self, m: mujoco.MjModel, config: mink.Configuration, call: str) -> tuple[list, list]:
        """Tasks and checks the solver adds to the targets' own (none: the whole-body solver holds the
        feet and the centre of mass), made from the start configuration."""
        return [], []

    def frame_pose(self, frame: str, kind: str = "site") -> tuple[np.ndarray, np.ndarray]:
        """(position (3,) m, orientation quaternion (w, x, y, z)) of a frame now, in the world frame."""
        view = self._link.core.mj
        fid = self._frame_id(view.model, frame, kind, f"{self.CALL}.frame_pose", "frame")
        xpos = getattr(view.data, {"site": "site_xpos", "body": "xpos", "geom": "geom_xpos"}[kind])[fid]
        xmat = getattr(view.data, {"site": "site_xmat", "body": "xmat", "geom": "geom_xmat"}[kind])[fid]
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, xmat)
        return np.array(xpos), quat

    def _frame_id(self, m: mujoco.MjModel, frame: Any, kind: Any, call: str, field: str) -> int:
        if kind not in KINDS:
            raise _fail(call, field.rsplit(".", 1)[0] + ".kind" if "." in field else "kind",
                        f"a frame is one of {', '.join(KINDS)}, got {kind!r}")
        obj = {"site": mujoco.mjtObj.mjOBJ_SITE, "body": mujoco.mjtObj.mjOBJ_BODY,
               "geom": mujoco.mjtObj.mjOBJ_GEOM}[kind]
        fid = mujoco.mj_name2id(m, obj, frame) if isinstance(frame, str) else -1
        if fid < 0:
            count = {"site": m.nsite, "body": m.nbody, "geom": m.ngeom}[kind]
            known = [n for n in (mujoco.mj_id2name(m, obj, i) for i in range(count)) if n]
            listed = ", ".join(known[:10]) + (", ..." if len(known) > 10 else "") if known else "none"
            raise _fail(call, field, f"no {kind} {frame!r} in the model" + did_you_mean(str(frame), known)
                        + f"; {kind}s: {listed}")
        return fid

    # -- solving ------------------------------------------------------------------------------------------
    def solve(self, targets: Target | Sequence[Target], *,
              start: Sequence[float] | Mapping[str, float] | IkResult | None = None,
              tol_m: float = 1e-3, tol_rad: float = 1e-2, max_iters: int = 400,
              damping: float = 1e-4) -> IkResult:
        """The joint values that bring every target's frame to its target (see the module docstring).

        ``start``: the joints' values to search from (SI, the joints' order, or ``{joint: value}``, or an
        earlier result: its whole configuration; default: where the core has them now). ``tol_m`` /
        ``tol_rad``: how close counts as reached. ``max_iters``: iterations at most (each one quadratic
        program); the search also stops when it no longer gets closer. ``damping``: mink's
        Levenberg-Marquardt damping (near singular poses).
        """
        call = f"{self.CALL}.solve"
        targets = [targets] if isinstance(targets, Target) else list(targets)
        if not targets:
            raise _fail(call, "targets", "no target given")
        for name, value in (("tol_m", tol_m), ("tol_rad", tol_rad), ("damping", damping)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise _fail(call, name, f"expected a number above 0, got {value!r}")
        if isinstance(max_iters, bool) or not isinstance(max_iters, int) or max_iters < 1:
            raise _fail(call, "max_iters", f"expected a whole number of at least 1, got {max_iters!r}")
        problem = self._current()
        m = problem.view.model
        tasks, checks, follows = self._tasks(m, targets, call)
        config = mink.Configuration(m, self._start(problem, start, call))
        more_tasks, more_checks = self._support(m, config, call)
        tasks, checks = tasks + more_tasks, checks + more_checks
        best_q, best_errors = config.q.copy(), tuple(check(config) for check in checks)  # the start is a candidate
        best_score = _score(best_errors)
        stalled, iterations = 0, 0
        while iterations < max_iters:
            iterations += 1
            for follow in follows:
                follow(config)
            qp = mink.build_ik(config, tasks, 1.0, damping, problem.limits, problem.constraints)
            solution = qpsolvers.solve_problem(qp, solver=SOLVER)
            if not solution.found:
                break
            config.integrate_inplace(solution.x, 1.0)
            errors = tuple(check(config) for check in checks)
            score = _score(errors)
            stalled = stalled + 1 if score > best_score * (1 - 1e-6) else 0
            if score < best_score:
                best_score, best_q, best_errors = score, config.q.copy(), errors
            if all(e.position_m <= POLISH * tol_m and e.orientation_rad <= POLISH * tol_rad for e in errors):
                break
            if stalled >= STALL:
                break
        reached = all(e.position_m <= tol_m and e.orientation_rad <= tol_rad for e in best_errors)
        q = best_q[problem.qpos_adr].copy()
        q.setflags(write=False)
        best_q.setflags(write=False)
        return IkResult(reached, q, self.joints, self.slides, best_errors, iterations,
                        self._message(reached, best_errors, tol_m, tol_rad), best_q)

    @staticmethod
    def _message(reached: bool, errors: tuple[FrameError, ...], tol_m: float, tol_rad: float) -> str:
        if reached:
            worst = max(errors, key=lambda e: e.position_m)
            return f"reached: every frame within {tol_m * 1000:g} mm and {tol_rad:g} rad " \
                   f"(the worst, {worst.frame!r}, {worst.position_m * 1000:.3g} mm away)"
        missed = [e for e in errors if e.position_m > tol_m or e.orientation_rad > tol_rad]
        parts = [f"{e.frame!r} stays {e.position_m * 1000:.1f} mm and {e.orientation_rad:.3f} rad from its target"
                 for e in missed]
        return "out of reach: in the best pose found, " + "; ".join(parts) + \
            f" (tolerances {tol_m * 1000:g} mm, {tol_rad:g} rad)"

    def _start(self, problem: _Problem, start: Any, call: str) -> np.ndarray:
        q = np.array(problem.view.data.qpos, dtype=np.float64)
        if start is None:
            return q
        if isinstance(start, IkResult):
            if start.q_full is None or start.q_full.shape != q.shape:
                raise _fail(call, "start", "that result is of another model (the core's structure changed since)")
            return np.array(start.q_full, dtype=np.float64)
        n = len(self.joints)
        if isinstance(start, Mapping):
            for key, value in start.items():
                if key not in self.joints:
                    raise _fail(call, f"start.{key}", f"no joint {key!r} among the solver's joints"
                                + did_you_mean(str(key), self.joints))
                q[problem.qpos_adr[self.joints.index(key)]] = _number(value, call, f"start.{key}")
            return q
        values = _vector(start, n, call, "start")
        q[problem.qpos_adr] = values
        return q

    def _tasks(self, m: mujoco.MjModel, targets: list[Target], call: str) -> tuple[list, list, list]:
        """mink's tasks for the targets, a check of each target (a `FrameError` of a configuration), and
        what must be done before each iteration: a position without an orientation is a frame task whose
        target orientation follows the frame's own, so that its error is the position's alone (mink's
        frame error is the SE(3) logarithm, whose translation part mixes in any rotation left)."""
        tasks: list = []
        checks: list = []
        follows: list = []
        for i, t in enumerate(targets):
            field = f"targets[{i}]"
            if not isinstance(t, Target):
                raise _fail(call, field, f"expected a Target, got {type(t).__name__}")
            fid = self._frame_id(m, t.frame, t.kind, call, f"{field}.frame")
            pos = None if t.pos is None else _vector(t.pos, 3, call, f"{field}.pos")
            quat = None if t.quat is None else _unit(_vector(t.quat, 4, call, f"{field}.quat"), call, f"{field}.quat",
                                                     "a quaternion of length zero is no orientation")
            if (t.axis is None) != (t.direction is None):
                raise _fail(call, f"{field}.{'direction' if t.direction is None else 'axis'}",
                            "axis and direction go together: the frame's axis, and the world direction to point it")
            if quat is not None and t.axis is not None:
                raise _fail(call, f"{field}.axis", "give an orientation (quat) or an axis to point, not both")
            axis = None if t.axis is None else _unit(_vector(t.axis, 3, call, f"{field}.axis"), call, f"{field}.axis")
            direction = None if t.direction is None else _unit(_vector(t.direction, 3, call, f"{field}.direction"),
                                                               call, f"{field}.direction")
            if pos is None and quat is None and axis is None:
                raise _fail(call, field, "a target needs a position (pos), an orientation (quat), or an axis and "
                            "a direction")
            if pos is not None or quat is not None:
                task = mink.FrameTask(t.frame, t.kind, position_cost=1.0 if pos is not None else 0.0,
                                      orientation_cost=ORIENTATION_COST if quat is not None else 0.0,
                                      lm_damping=LM_DAMPING)
                rotation = mink.SO3(quat) if quat is not None else mink.SO3.identity()
                translation = pos if pos is not None else np.zeros(3)
                task.set_target(mink.SE3.from_rotation_and_translation(rotation, translation))
                tasks.append(task)
                if quat is None:
                    follows.append(_follower(task, t.frame, t.kind, translation))
            if axis is not None:
                align = mink.AxisAlignTask(t.frame, t.kind, axis=axis, cost=ORIENTATION_COST, lm_damping=LM_DAMPING)
                align.set_target(direction)
                tasks.append(align)
            checks.append(_checker(t.frame, t.kind, fid, pos, quat, axis, direction))
        return tasks, checks, follows


def _follower(task: mink.FrameTask, frame: str, kind: str, pos: np.ndarray) -> Any:
    """Before an iteration: the task's target is ``pos`` in the frame's current orientation."""

    def follow(config: mink.Configuration) -> None:
        now = config.get_transform_frame_to_world(frame, kind)
        task.set_target(mink.SE3.from_rotation_and_translation(now.rotation(), pos))

    return follow


def _score(errors: tuple[FrameError, ...]) -> float:
    """How far a pose is from the targets, as the tasks weigh it (the best pose is the one it is least for)."""
    return sum(e.position_m ** 2 + (ORIENTATION_COST * e.orientation_rad) ** 2 for e in errors)


def _checker(frame: str, kind: str, fid: int, pos: np.ndarray | None, quat: np.ndarray | None,
             axis: np.ndarray | None, direction: np.ndarray | None) -> Any:
    """A function of a configuration: how far the frame is from its target (a `FrameError`)."""
    xpos_attr = {"site": "site_xpos", "body": "xpos", "geom": "geom_xpos"}[kind]
    xmat_attr = {"site": "site_xmat", "body": "xmat", "geom": "geom_xmat"}[kind]
    target_rot = None
    if quat is not None:
        target_rot = np.empty(9)
        mujoco.mju_quat2Mat(target_rot, quat)
        target_rot = target_rot.reshape(3, 3)

    def check(config: mink.Configuration) -> FrameError:
        d = config.data
        x = getattr(d, xpos_attr)[fid]
        r = getattr(d, xmat_attr)[fid].reshape(3, 3)
        e_pos = float(np.linalg.norm(x - pos)) if pos is not None else 0.0
        e_rot = 0.0
        if target_rot is not None:
            cos = (np.trace(target_rot.T @ r) - 1.0) / 2.0
            e_rot = float(math.acos(min(1.0, max(-1.0, cos))))
        elif axis is not None:
            cos = float(np.dot(r @ axis, direction))
            e_rot = float(math.acos(min(1.0, max(-1.0, cos))))
        return FrameError(frame, e_pos, e_rot)

    return check


def _number(value: Any, call: str, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _fail(call, field, f"expected a finite number, got {value!r}")
    return float(value)


def _vector(value: Any, n: int, call: str, field: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(call, field, f"expected {n} numbers, got {value!r}") from None
    if arr.shape != (n,):
        raise _fail(call, field, f"expected {n} numbers, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise _fail(call, field, f"expected finite numbers, got {arr.tolist()}")
    return arr


def _unit(v: np.ndarray, call: str, field: str, zero: str = "a vector of length zero has no direction") -> np.ndarray:
    norm = float(np.linalg.norm(v))
    if norm < 1e-9:
        raise _fail(call, field, f"{zero} ({v.tolist()})")
    return v / norm
