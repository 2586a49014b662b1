"""Inputs of the Exudyn core's systems that act on free bodies: a wrench held for the tick and a
velocity set at its start (the ``B.wrench`` and ``B.velocity`` ports of `PhysicsCore`).

A free body rides on a free carrier, a rigid body node at the carrier's centre of mass (alone, or
merged with what `make_joint` welded to it). A wrench on a body becomes a wrench on its carrier at
the carrier's centre of mass: its force as a change of the carrier's mass-proportional load (gravity
plus force over mass, so a carrier without a push keeps exactly gravity) and its torque, plus the
moment of the force about the centre of mass when the body sits away from it, as a torque load. A
velocity request sets the carrier's node velocities so that the body's origin moves (and the carrier
turns) as asked. Bodies frozen, or welded to something static or to a jointed link, take neither.

Nothing here is state: the loads are set again from the inputs before every step (only when they
change), and a velocity request is applied from the inputs at every step it holds a value.
"""

from __future__ import annotations

import numpy as np

from dynabrain.orchestrator.kernel.core import requested_velocity

from . import geometry as geo


class Inputs:
    """The input half of `exudyn.system.System` (a mixin, like `exudyn.outputs.Outputs`)."""

    def _index_inputs(self) -> None:
        """Which free carrier each free body of the port layout moves, and where it sits on it."""
        self.pushes: list[tuple[int, int, np.ndarray | None]] = []
        """(row in the body input blocks, free carrier, body origin in the carrier frame or None at its
        centre of mass) of each free body that moves on a free carrier."""
        for row, body in enumerate(self.top.free_bodies()):
            frame = self.frames[body]
            if frame.kind == "free":
                arm = np.asarray(frame.pose[0], dtype=float)
                self.pushes.append((row, frame.index, None if not arm.any() else arm))
        # (``pushed``, the wrench on each free carrier now, and ``pushing``, whether one is not 0, are
        # made with the system: its parameters set its gravity loads from them)

    def gravity_load(self, i: int) -> list[float]:
        """The mass-proportional load of free carrier ``i``: gravity, plus its pushing force over its mass."""
        force = self.pushed[i, :3]
        if not force.any():
            return list(self.gravity)
        return [float(x) for x in np.asarray(self.gravity) + force / self.free_mass[i]]

    def push(self, wrench: np.ndarray) -> None:
        """Set the loads of the free carriers from the wrench inputs (``body_wrench``, flat) for the next step."""
        rows = wrench.reshape(-1, 6)
        total = np.zeros_like(self.pushed)
        for row, i, arm in self.pushes:
            total[i] += rows[row]
            if arm is not None:  # the force's moment about the carrier's centre of mass
                total[i, 3:] += np.cross(self._rotation(i) @ arm, rows[row, :3])
        mbs = self.mbs
        for i in np.flatnonzero((total != self.pushed).any(axis=1)):
            self.pushed[i] = total[i]
            mbs.SetLoadParameter(self.free[i][2], "loadVector", self.gravity_load(i))
            mbs.SetLoadParameter(self.torque_loads[i], "loadVector", [float(x) for x in total[i, 3:]])
        self.pushing = bool(self.pushed.any())

    def set_velocities(self, request: np.ndarray) -> None:
        """Give each free body the velocity its input asks for (``body_velocity``, flat; NaN: left alone)."""
        rows = request.reshape(-1, 6)
        v = self._v.copy()
        changed = False
        for row, i, arm in self.pushes:
            k = self.free_index[i] + self._six
            rot = self._rotation(i)
            omega = rot @ v[k[3:]]  # the node's angular velocity is in its own frame
            arm_w = rot @ arm if arm is not None else None
            lin_now = v[k[:3]] if arm_w is None else v[k[:3]] + np.cross(omega, arm_w)
            lin, ang = requested_velocity(rows[row], lin_now, omega)
            if lin is None and ang is None:
                continue
            if ang is not None:
                v[k[3:]] = rot.T @ ang
                omega = ang
            if lin is not None or arm_w is not None:  # the body's origin keeps what was not asked for
                lin = lin_now if lin is None else lin
                v[k[:3]] = lin if arm_w is None else lin - np.cross(omega, arm_w)
            changed = True
        if changed:
            self.mbs.systemData.SetODE2Coordinates_t(v)
            self.read()

    def _rotation(self, i: int) -> np.ndarray:
        """The rotation matrix (carrier frame -> world) of free carrier ``i`` now (after `read`)."""
        return geo.quat_to_mat(geo.rotvec_to_quat(self._x[self.free_index[i] + 3:self.free_index[i] + 6]))
