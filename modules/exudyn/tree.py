"""Kinematic trees of the Exudyn core: a chain (or tree) of bodies on hinge and slide joints, hanging
from the world or from a static body, as one ``ObjectKinematicTree`` in minimal coordinates.

Each link's frame is its joint frame: origin at the joint's anchor, z along its axis (so every joint
is Exudyn's ``RevoluteZ`` or ``PrismaticZ``); a link's pose is its parent's, times the constant
offset and rotation between the two joint frames at q = 0 (from the scene), times the joint's
motion. A link carries its body and the bodies fixed to it (and bodies welded to it), as one mass.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import exudyn as exu
import numpy as np

from . import geometry as geo
from .plan import Plan
from .topology import Topology


class TreeSpec:
    """The parameters of one kinematic tree: parents, joint offsets and rotations at q = 0, joint types
    and damping, and each link's mass properties and members (pose in its joint frame)."""

    def __init__(self, top: Topology, plan: Plan, links: list[str],
                 mass_of: Callable[[dict[str, geo.Pose]], tuple[float, np.ndarray, np.ndarray]]):
        index = {n: i for i, n in enumerate(links)}
        x_wj: dict[str, geo.Pose] = {}
        self.parents, self.offsets, self.rotations, self.kinds = [], [], [], []
        self.masses, self.coms, self.inertias, self.damping, self.members = [], [], [], [], []
        self.joints = [top.joint_of[n] for n in links]
        for link in links:
            j = top.spec[link].joint
            x_oj = (np.asarray(j.anchor, dtype=float), geo.mat_to_quat(geo.frame_z(j.axis)))
            x_wj[link] = geo.compose(top.world[link], x_oj)
            p = top.spec[link].parent
            while p is not None and p not in index:
                p = top.spec[p].parent
            self.parents.append(index[p] if p is not None else -1)
            rel = x_wj[link] if p is None else geo.compose(geo.inverse(x_wj[p]), x_wj[link])
            self.offsets.append(rel[0])
            self.rotations.append(geo.quat_to_mat(rel[1]))
            self.kinds.append(exu.JointType.RevoluteZ if j.kind == "hinge" else exu.JointType.PrismaticZ)
            inv = geo.inverse(x_oj)
            members = {m: geo.compose(inv, x) for m, x in plan.carriers[link].members.items()}
            mass, com, inertia = mass_of(members)
            self.masses.append(mass)
            self.coms.append(com)
            self.inertias.append(inertia)
            self.damping.append(float(j.damping))
            self.members.append(members)

    def axis_inertia(self, i: int, kind: str) -> float:
        """What resists motion at joint i of its own link: the inertia about the axis, or the mass."""
        com, inertia = self.coms[i], self.inertias[i]
        if kind == "hinge":
            return float(inertia[2, 2] + self.masses[i] * (com[0] ** 2 + com[1] ** 2))
        return float(self.masses[i])


def _qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)


def _rotate(q, v):
    w, x, y, z = q
    vx, vy, vz = v
    tx, ty, tz = 2 * (y * vz - z * vy), 2 * (z * vx - x * vz), 2 * (x * vy - y * vx)
    return (vx + w * tx + y * tz - z * ty, vy + w * ty + z * tx - x * tz, vz + w * tz + x * ty - y * tx)


class Kinematics:
    """Forward kinematics of one tree, in plain floats (a few links: cheaper than numpy or asking Exudyn):
    world pose and velocity of every link frame from the joint coordinates."""

    def __init__(self, spec: TreeSpec):
        self.parents = list(spec.parents)
        self.offsets = [tuple(map(float, o)) for o in spec.offsets]
        self.rotations = [tuple(map(float, geo.mat_to_quat(r))) for r in spec.rotations]
        self.hinge = [k == exu.JointType.RevoluteZ for k in spec.kinds]

    def frames(self, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Positions (n, 3), quaternions (n, 4), velocities (n, 3) and angular velocities (n, 3)."""
        return tuple(np.array(f) for f in self.frame_lists(q, qd))

    def carry(self, q: np.ndarray, qd: np.ndarray, members, pos: np.ndarray, quat: np.ndarray, lin: np.ndarray,
              ang: np.ndarray) -> None:
        """Write the pose and velocity of bodies ``(row, link, position, quaternion in the link frame)``."""
        p_l, q_l, v_l, w_l = self.frame_lists(q, qd)
        for row, i, t, qb in members:
            arm = _rotate(q_l[i], t)
            p, v, w = p_l[i], v_l[i], w_l[i]
            pos[row] = (p[0] + arm[0], p[1] + arm[1], p[2] + arm[2])
            quat[row] = _qmul(q_l[i], qb)
            lin[row] = (v[0] + w[1] * arm[2] - w[2] * arm[1], v[1] + w[2] * arm[0] - w[0] * arm[2],
                        v[2] + w[0] * arm[1] - w[1] * arm[0])
            ang[row] = w

    def frame_lists(self, q: np.ndarray, qd: np.ndarray) -> tuple[list, list, list, list]:
        """`frames` as lists of float tuples."""
        pos, quat, vel, omega = [], [], [], []
        zero, unit = (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)
        for i, parent in enumerate(self.parents):
            pp, qp, vp, wp = (pos[parent], quat[parent], vel[parent], omega[parent]) if parent >= 0 else \
                (zero, unit, zero, zero)
            qi, qdi = float(q[i]), float(qd[i])
            o = _rotate(qp, self.offsets[i])
            base = _qmul(qp, self.rotations[i])
            if self.hinge[i]:
                qq = _qmul(base, (math.cos(0.5 * qi), 0.0, 0.0, math.sin(0.5 * qi)))
                axis = _rotate(qq, (0.0, 0.0, 1.0))
                p = (pp[0] + o[0], pp[1] + o[1], pp[2] + o[2])
                w = (wp[0] + axis[0] * qdi, wp[1] + axis[1] * qdi, wp[2] + axis[2] * qdi)
                slide = zero
            else:
                qq = base
                axis = _rotate(qq, (0.0, 0.0, 1.0))
                p = (pp[0] + o[0] + axis[0] * qi, pp[1] + o[1] + axis[1] * qi, pp[2] + o[2] + axis[2] * qi)
                w = wp
                slide = (axis[0] * qdi, axis[1] * qdi, axis[2] * qdi)
            r = (p[0] - pp[0], p[1] - pp[1], p[2] - pp[2])
            v = (vp[0] + wp[1] * r[2] - wp[2] * r[1] + slide[0], vp[1] + wp[2] * r[0] - wp[0] * r[2] + slide[1],
                 vp[2] + wp[0] * r[1] - wp[1] * r[0] + slide[2])
            pos.append(p)
            quat.append(qq)
            vel.append(v)
            omega.append(w)
        return pos, quat, vel, omega
