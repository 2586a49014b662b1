"""Outputs of the Exudyn core's systems: where every body, joint and cable end is, from Exudyn's
coordinates, written into the core's (n, 3) and (n, 4) arrays with a few array operations per kind
of carrier (free rigid bodies, links of kinematic trees, the static world, cables).

A free carrier's coordinates are its node's position and rotation vector (Lie-group node), its
velocities the node's velocity and angular velocity in the node frame; a link's frame comes from
the tree's forward kinematics (`exudyn.tree.Kinematics`); a body is at a fixed pose in its carrier.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry as geo


@dataclass
class Frame:
    """How a body's pose follows from its carrier: carrier kind and index, pose in the carrier frame."""

    kind: str
    index: int
    pose: geo.Pose


class Outputs:
    """The output half of `exudyn.system.System` (a mixin: it reads the system's maps and coordinates)."""

    def _index_outputs(self) -> None:
        mbs, top = self.mbs, self.top
        self.free_index = np.array([mbs.GetNodeODE2Index(node) for node, _b, _l in self.free], dtype=int)
        groups: dict[str, list[tuple[int, Frame]]] = {"free": [], "link": [], "world": [], "cable": []}
        for row, body in enumerate(top.bodies):
            groups[self.frames[body].kind].append((row, self.frames[body]))
        self.groups = {}
        for kind, members in groups.items():
            rows = np.array([r for r, _f in members], dtype=int)
            index = np.array([f.index for _r, f in members], dtype=int)
            t = np.array([f.pose[0] for _r, f in members]).reshape(-1, 3)
            q = np.array([f.pose[1] for _r, f in members]).reshape(-1, 4)
            self.groups[kind] = (rows, index, t, q)
        self.cable_index = [np.array([mbs.GetNodeODE2Index(n) for n in c.nodes], dtype=int) for c in self.cables]
        rows, coords, frozen_rows, frozen_q = [], [], [], []
        for r, joint in enumerate(top.qjoints):
            if joint in self.joint_index:
                tree, i = self.joint_index[joint]
                rows.append(r)
                coords.append(mbs.GetNodeODE2Index(self.trees[tree]["node"]) + i)
            else:
                frozen_rows.append(r)
                frozen_q.append(self.plan.frozen_joints.get(joint, 0.0))
        self.q_rows, self.q_coords = np.array(rows, dtype=int), np.array(coords, dtype=int)
        self.frozen_q_rows, self.frozen_q = np.array(frozen_rows, dtype=int), np.array(frozen_q)
        self.force_rows = [np.array([top.qjoints.index(j) for j in t["joints"]], dtype=int) for t in self.trees]
        first = 0
        for t in self.trees:
            t["coords"] = mbs.GetNodeODE2Index(t["node"]) + np.arange(len(t["links"]))
            t["members"] = [(row, self.frames[b].index - first, tuple(map(float, self.frames[b].pose[0])),
                             tuple(map(float, self.frames[b].pose[1])))
                            for row, b in enumerate(top.bodies) if self.frames[b].kind == "link"
                            and first <= self.frames[b].index < first + len(t["links"])]
            first += len(t["links"])
        self._six = np.arange(6)
        self._identity = {k: bool(np.allclose(g[2], 0.0) and np.allclose(g[3], [1.0, 0.0, 0.0, 0.0]))
                          for k, g in self.groups.items()}
        self.read()

    def write_static(self, pos: np.ndarray, quat: np.ndarray, lin: np.ndarray, ang: np.ndarray,
                     q: np.ndarray, qd: np.ndarray) -> None:
        """Outputs that do not change while this structure is active: static and frozen bodies and joints."""
        rows, _i, t, qq = self.groups["world"]
        pos[rows], quat[rows], lin[rows], ang[rows] = t, qq, 0.0, 0.0
        q[self.frozen_q_rows], qd[self.frozen_q_rows] = self.frozen_q, 0.0

    def read(self) -> None:
        """Fetch coordinates and velocities after a step (for `diverged` and `write`)."""
        sd = self.mbs.systemData
        self._x, self._v = sd.GetODE2Coordinates(), sd.GetODE2Coordinates_t()

    def write(self, pos: np.ndarray, quat: np.ndarray, lin: np.ndarray, ang: np.ndarray,
              q: np.ndarray, qd: np.ndarray) -> None:
        """Poses and velocities of every moving body ((n, 3) and (n, 4) arrays), joint values, from `read`."""
        x, v = self._x, self._v
        rows, index, t, qb = self.groups["free"]
        if len(rows):
            k = self.free_index[index][:, None] + self._six
            xs, vs = x[k], v[k]
            qc = geo.rotvec_to_quat_n(xs[:, 3:])
            _carry(pos, quat, lin, ang, rows, xs[:, :3], qc, vs[:, :3], geo.rotate_n(qc, vs[:, 3:]), t, qb,
                   self._identity["free"])
        for tree in self.trees:  # a few links: plain floats beat array operations
            tree["kinematics"].carry(x[tree["coords"]], v[tree["coords"]], tree["members"], pos, quat, lin, ang)
        rows, index, _t, _q = self.groups["cable"]
        for row, c in zip(rows, index, strict=True):
            tip = self.cable_index[c][-1] + self._six
            now = self.cables[c].ref[-1] + x[tip]
            pos[row], quat[row] = now[:3], geo.direction_quat(now[3:])
            lin[row], ang[row] = v[tip[:3]], 0.0
        q[self.q_rows], qd[self.q_rows] = x[self.q_coords], v[self.q_coords]

    def cable_coords(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Node coordinates (n+1, 6: position, slope) and their velocities of a cable, now."""
        for c, parts in enumerate(self.cables):
            if parts.name == name:
                if parts.frozen:
                    return parts.coords.copy(), np.zeros_like(parts.coords)
                sd = self.mbs.systemData
                k = self.cable_index[c][:, None] + np.arange(6)
                return parts.ref + sd.GetODE2Coordinates()[k], sd.GetODE2Coordinates_t()[k]
        raise KeyError(name)

    # -- parameters and inputs ------------------------------------------------------------------------------------
    def diverged(self) -> str | None:
        """What went bad in the last step (NaN, infinite or beyond 1e10), or None (after `read`)."""
        if np.abs(self._x).max(initial=0.0) < 1e10 and np.abs(self._v).max(initial=0.0) < 1e10:
            return None
        x = np.concatenate([self._x, self._v])
        bad = np.flatnonzero(~(np.abs(x) < 1e10))
        n = len(x) // 2
        coord = int(bad[0]) % n
        return f"the {'position' if bad[0] < n else 'velocity'} of {self._owner_of(coord)}"

    def _owner_of(self, coord: int) -> str:
        for i, start in enumerate(self.free_index):
            if start <= coord < start + 6:
                owner = next(b for b, f in self.frames.items() if f.kind == "free" and f.index == i
                             and self.plan.carrier_of.get(b) == b)
                return f"body {owner!r}"
        for joint, row in zip(self.top.qjoints, range(len(self.top.qjoints)), strict=True):
            if row in self.q_rows and self.q_coords[list(self.q_rows).index(row)] == coord:
                return f"joint {joint!r}"
        for c, idx in enumerate(self.cable_index):
            if len(idx) and idx[0] <= coord < idx[-1] + 6:
                return f"cable {self.cables[c].name!r}"
        return f"coordinate {coord}"



def _carry(pos, quat, lin, ang, rows, pc, qc, vc, omega, t, qb, identity: bool) -> None:
    """Poses and velocities of bodies at ``t``, ``qb`` in carriers at ``pc``, ``qc`` moving at ``vc`` with
    angular velocity ``omega`` (world frame); ``identity`` when every body is at its carrier's origin."""
    if identity:
        pos[rows], quat[rows], lin[rows], ang[rows] = pc, qc, vc, omega
        return
    arm = geo.rotate_n(qc, t)
    pos[rows] = pc + arm
    quat[rows] = geo.qmul_n(qc, qb)
    lin[rows] = vc + geo.cross_n(omega, arm)
    ang[rows] = omega
