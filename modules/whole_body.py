"""Whole-body inverse kinematics for a humanoid: hand targets to the servo's angle-vectors, feet planted.

The paper's last step (EusDyna, Fig. 22: "generates robot whole body motion ... using inverse
kinematics and stabilize the pose"). A brain says where a hand should be; the solver finds the angles
of every joint of the robot's servo that put it there while

- both feet stay where they are (position and orientation of each foot body),
- the centre of mass stays over the middle of the support polygon (the soles' convex hull), so that
  the pose is statically balanced: standing still in it, the ZMP is the centre of mass's projection,
- the joints stay near the pose the search starts from (a posture task: the least motion that does it),
- the joints keep their ranges.

The robot's floating base (its free joint) is free in the search: to reach low the pelvis lowers and
leans, as a person bends at the hips and knees. The servo then drives the joints to the angles found
and, the feet planted, the base follows where the solver put it. Everything else in the model (tables,
blocks, a drawer) is held where it is.

    wb = WholeBody.for_servo(world, "servo")                      # the kid: feet l_foot and r_foot
    above = wb.solve([Target("r_hand_tip", pos=[0.2, -0.05, 0.33])])
    push = wb.solve([Target("r_hand_tip", pos=[0.2, 0.05, 0.33])], start=above)   # chained from it
    if above.reached and push.reached:
        world.set("servo.sequence", [above.step("0.8s"), push.step("0.6s")])
    else:
        print(above.message, above.com_margin_m)

Solved by mink on the MuJoCo core's current model (`modules.ik`, whose solver this extends with the
free base and the support tasks). ``reached`` holds when every hand target is within the tolerances,
both feet stayed put (within the tolerances), and the centre of mass stays within ``com_slack_m`` of
the support polygon's middle; ``com_margin_m`` says how far inside the polygon it is. A pose that is not
reached is still the best found, never an error; bad input (a foot or frame the model lacks, a robot
without a free base) raises `PoseError` naming the call and the field.

The centre of mass is the robot's own (the subtree of its base), not the model's: mink's ``ComTask``
takes body 1's subtree, which in a scene with a table first is the table.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import mink
import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.suggest import did_you_mean

from .ik import FrameError, IkError, IkResult, InverseKinematics, Target
from .servo import Servo
from .support import convex_hull, polygon_centre, polygon_margin

__all__ = ["PoseError", "Target", "WholeBody", "WholeBodyResult"]

FEET_COST = 10.0
"""Weight of a foot's pose error against a hand's (1 per m): the feet hold first."""
COM_COST = 5.0
"""Weight of the centre of mass's horizontal distance from the support polygon's middle (per m)."""
POSTURE_COST = 0.005
"""Weight of each joint's distance from the starting pose (per rad): the least motion that reaches."""
UPRIGHT_COST = 0.02
"""Weight of the base's tilt from upright (per rad): a mild preference; bending at the hips tilts it."""
COM_SLACK_M = 0.01
"""How far (m) the centre of mass may stray from the support polygon's middle in a reached pose."""
_FREE = int(mujoco.mjtJoint.mjJNT_FREE)


class PoseError(IkError):
    """A whole-body problem the solver cannot take (an unknown foot, a robot without a free base)."""


@dataclass(frozen=True)
class WholeBodyResult(IkResult):
    """`IkResult` (the servo's joints, ``pose()``, ``step()``, ``q_full``) and the balance of the pose:
    ``com_margin_m``, the signed distance (m) of the centre of mass's ground projection inside the
    support polygon (negative: outside); ``com_xy`` (m) and the polygon ``support`` (x, y vertices)."""

    com_margin_m: float = 0.0
    com_xy: tuple[float, float] = (0.0, 0.0)
    support: tuple[tuple[float, float], ...] = ()


class _RobotCom(mink.Task):
    """The centre of mass of one robot (the subtree of its base body) towards a target, per axis."""

    k: int = 3

    def __init__(self, root: int, cost: Sequence[float], target: np.ndarray):
        super().__init__(cost=np.asarray(cost, dtype=np.float64), gain=1.0, lm_damping=1.0)
        self._root = root
        self._target = np.asarray(target, dtype=np.float64)

    def compute_error(self, configuration: mink.Configuration) -> np.ndarray:
        return configuration.data.subtree_com[self._root] - self._target

    def compute_jacobian(self, configuration: mink.Configuration) -> np.ndarray:
        jac = np.zeros((3, configuration.model.nv))
        mujoco.mj_jacSubtreeCom(configuration.model, configuration.data, jac, self._root)
        return jac


class WholeBody(InverseKinematics):
    """Hand targets to the servo's joint angles with the feet planted and the pose balanced (see the
    module docstring). ``feet``: the bodies the robot stands on; ``com_slack_m``: how far the centre of
    mass may stray from the support polygon's middle in a reached pose."""

    CALL = "WholeBody"

    def __init__(self, core: Any, joints: Sequence[str] = (), *, feet: Sequence[str] = ("l_foot", "r_foot"),
                 com_slack_m: float = COM_SLACK_M):
        super().__init__(core, joints)
        if isinstance(feet, str) or not feet:
            raise PoseError(f"{self.CALL} [feet]: give the bodies the robot stands on, e.g. ('l_foot', 'r_foot')")
        if not (isinstance(com_slack_m, (int, float)) and math.isfinite(com_slack_m) and com_slack_m >= 0):
            raise PoseError(f"{self.CALL} [com_slack_m]: expected a distance of 0 or more, got {com_slack_m!r}")
        self.feet = tuple(feet)
        self.com_slack_m = float(com_slack_m)
        m = self._link.model
        for i, foot in enumerate(self.feet):
            self._body(m, foot, f"feet[{i}]")
        self._base(m)

    @classmethod
    def for_servo(cls, world: Any, servo: str = "servo", *, feet: Sequence[str] = ("l_foot", "r_foot"),
                  com_slack_m: float = COM_SLACK_M) -> WholeBody:
        """A solver for the joints of the world's servo module ``servo``, in its order."""
        module = world.modules.get(servo)
        if not isinstance(module, Servo):
            known = [n for n, m in world.modules.items() if isinstance(m, Servo)]
            raise PoseError(f"{cls.CALL}.for_servo [servo]: no servo module {servo!r} in the world"
                            + did_you_mean(servo, known) + f"; servos: {', '.join(known) or 'none'}")
        return cls(world.core, module.joints, feet=feet, com_slack_m=com_slack_m)

    # -- the model ----------------------------------------------------------------------------------------
    def _body(self, m: mujoco.MjModel, name: str, field: str) -> int:
        bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name) if isinstance(name, str) else -1
        if bid < 0:
            known = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, i) or "" for i in range(m.nbody)]
            raise PoseError(f"{self.CALL} [{field}]: no body {name!r} in the model" + did_you_mean(str(name), known))
        return bid

    def _base(self, m: mujoco.MjModel) -> tuple[int, int]:
        """(the robot's root body, its free joint): the body under the world that carries the joints."""
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, self.joints[0])
        body = int(m.jnt_bodyid[jid])
        while int(m.body_parentid[body]) != 0:
            body = int(m.body_parentid[body])
        for j in range(int(m.body_jntadr[body]), int(m.body_jntadr[body]) + int(m.body_jntnum[body])):
            if int(m.jnt_type[j]) == _FREE:
                return body, j
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body)
        raise PoseError(f"{self.CALL} [joints]: the robot's root body {name!r} has no free joint: a whole-body "
                        "solver moves a floating base (use InverseKinematics for a fixed robot)")

    def _free_dofs(self, m: mujoco.MjModel) -> np.ndarray:
        _, free = self._base(m)
        return np.arange(int(m.jnt_dofadr[free]), int(m.jnt_dofadr[free]) + 6, dtype=np.intp)

    def _support_polygon(self, m: mujoco.MjModel, d: mujoco.MjData) -> list[list[float]]:
        """The soles' convex hull (x, y): the bottom corners of each foot's box geoms (a geom of another
        shape counts by its centre)."""
        points: list[np.ndarray] = []
        for foot in self.feet:
            bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, foot)
            for g in range(int(m.body_geomadr[bid]), int(m.body_geomadr[bid]) + int(m.body_geomnum[bid])):
                centre, rot = d.geom_xpos[g], d.geom_xmat[g].reshape(3, 3)
                if int(m.geom_type[g]) != int(mujoco.mjtGeom.mjGEOM_BOX):
                    points.append(centre.copy())
                    continue
                sx, sy, sz = m.geom_size[g]
                for cx in (-sx, sx):
                    for cy in (-sy, sy):
                        points.append(centre + rot @ np.array([cx, cy, -sz]))
        return convex_hull(np.array(points))

    # -- the problem --------------------------------------------------------------------------------------
    def _support(self, m: mujoco.MjModel, config: mink.Configuration, call: str) -> tuple[list, list]:
        d = config.data
        root, _ = self._base(m)
        tasks: list = []
        checks: list = []
        for foot in self.feet:
            task = mink.FrameTask(foot, "body", position_cost=FEET_COST, orientation_cost=FEET_COST, lm_damping=1.0)
            pose = config.get_transform_frame_to_world(foot, "body")
            task.set_target(pose)
            tasks.append(task)
            checks.append(_foot_check(m, foot, pose))
        hull = self._support_polygon(m, d)
        cx, cy = _centroid(hull)
        tasks.append(_RobotCom(root, (COM_COST, COM_COST, 0.0), np.array([cx, cy, 0.0])))
        checks.append(_com_check(root, (cx, cy), self.com_slack_m))
        cost = np.zeros(m.nv)
        cost[self._current().dof_adr] = POSTURE_COST
        posture = mink.PostureTask(m, cost=cost)
        posture.set_target(config.q.copy())
        tasks.append(posture)
        upright = mink.FrameTask(root, "body", position_cost=0.0, orientation_cost=UPRIGHT_COST)
        yaw = _yaw(d.xmat[root].reshape(3, 3))
        upright.set_target(mink.SE3.from_rotation_and_translation(mink.SO3.from_z_radians(yaw), np.zeros(3)))
        tasks.append(upright)
        return tasks, checks

    def solve(self, targets: Target | Sequence[Target], **kwargs: Any) -> WholeBodyResult:
        """The servo's joint angles that bring the targets' frames to their targets, feet planted and
        balanced (see the module and `InverseKinematics.solve` for the arguments; ``start`` may be an
        earlier result, to chain poses)."""
        result = super().solve(targets, **kwargs)
        m = self._current().view.model
        d = mujoco.MjData(m)
        d.qpos[:] = result.q_full
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        root, _ = self._base(m)
        hull = self._support_polygon(m, d)
        com = d.subtree_com[root]
        margin = polygon_margin(com, hull)
        message = result.message
        if margin < 0:
            message += f"; the centre of mass is {-margin * 1000:.0f} mm outside the support polygon"
        values = {f.name: getattr(result, f.name) for f in fields(IkResult)}
        values["message"] = message
        values["reached"] = result.reached and margin > 0
        return WholeBodyResult(**values, com_margin_m=float(margin), com_xy=(float(com[0]), float(com[1])),
                               support=tuple((float(x), float(y)) for x, y in hull))


def _centroid(hull: list[list[float]]) -> tuple[float, float]:
    """The area centroid of a convex polygon (the mean of its vertices is pulled towards where the
    hull has more of them: a nearly collinear corner on a heel's edge moved it 12 mm)."""
    if len(hull) < 3:
        return polygon_centre(hull)
    pts = np.asarray(hull, dtype=np.float64)
    x, y = pts[:, 0], pts[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2.0
    if abs(area) < 1e-12:
        return polygon_centre(hull)
    return float(((x + xn) * cross).sum() / (6 * area)), float(((y + yn) * cross).sum() / (6 * area))


def _yaw(rot: np.ndarray) -> float:
    return math.atan2(float(rot[1, 0]), float(rot[0, 0]))


def _foot_check(m: mujoco.MjModel, foot: str, pose: mink.SE3) -> Any:
    """How far a foot moved from where it stood (a `FrameError` of a configuration)."""
    bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, foot)
    pos = pose.translation().copy()
    rot = pose.rotation().as_matrix()

    def check(config: mink.Configuration) -> FrameError:
        d = config.data
        cos = (np.trace(rot.T @ d.xmat[bid].reshape(3, 3)) - 1.0) / 2.0
        return FrameError(foot, float(np.linalg.norm(d.xpos[bid] - pos)), float(math.acos(min(1.0, max(-1.0, cos)))))

    return check


def _com_check(root: int, centre: tuple[float, float], slack_m: float) -> Any:
    """How far (m) the robot's centre of mass strays beyond ``slack_m`` from the support's middle."""

    def check(config: mink.Configuration) -> FrameError:
        com = config.data.subtree_com[root]
        off = math.hypot(float(com[0]) - centre[0], float(com[1]) - centre[1])
        return FrameError("centre of mass", max(0.0, off - slack_m), 0.0)

    return check
