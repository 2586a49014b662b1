"""The ZMP sensor: centre of pressure of each foot and of both, and whether it lies in the support polygon.

Each foot's centre of pressure comes from the contact wrench the foot carries, measured by the
native 6-axis force/torque sensor at its ankle (a site of the foot body with MuJoCo ``force`` and
``torque`` sensors, found by itself), with the foot's own weight added: on a static stance the ZMP is
the projection of the whole body's centre of mass. The ZMP of the feet together is the pressure-
weighted mean of the loaded feet (exact when their soles are coplanar); a foot is loaded when it
touches something (the core's contact list) and carries at least ``min_force``. The support polygon
is the convex hull of the contact points of the loaded feet.

Why the wrench and not the contact list's forces: the MuJoCo core keeps its data after
``mj_step1``, where the contacts are those of the new state and their forces are not computed yet;
the force sensors hold the values of the last step (see `modules.mjaccess`).

Targets: the feet (bodies). Outputs:

==============  =======  ====  ======================================================================
port            shape    unit  meaning
==============  =======  ====  ======================================================================
``zmp``         (3,)     m     ZMP (centre of pressure of the loaded feet), world frame; NaN airborne
``cop``         (k, 3)   m     each foot's centre of pressure (NaN when not loaded); ``<foot>.cop``
``force``       (k,)     N     each foot's normal ground force; ``<foot>.force``
``inside``      ()       1     1 when the ZMP is at least ``min_margin`` inside the support polygon, else 0
``margin``      ()       m     signed distance from the ZMP to the polygon's edge (positive inside)
``center``      (3,)     m     centre of the support polygon (mean of its vertices)
==============  =======  ====  ======================================================================
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from dynabrain.orchestrator.module import Module, Param, Port, SetupContext

from .mjaccess import MujocoLink, fail
from .support import combined_pressure, convex_hull, foot_pressure, polygon_centre, polygon_margin

_SENS = mujoco.mjtSensor
_BOX, _SPHERE, _CAPSULE = (int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_SPHERE),
                           int(mujoco.mjtGeom.mjGEOM_CAPSULE))


class ZmpSensor(Module):
    """ZMP and support polygon of a set of feet (see the module docstring)."""

    PARAMS = (
        Param("min_force", 1.0, unit="N", runtime=True,
              doc="a foot is loaded when it touches something and carries at least this normal force"),
        Param("min_margin", 0.0, unit="m", dimension="length", runtime=True,
              doc="how far inside the support polygon the ZMP must be for `inside`"),
    )

    def _feet(self) -> list[str]:
        return list(self.targets)

    def outputs(self) -> list[Port]:
        feet = self._feet()
        k = len(feet)
        ports = [Port("zmp", (3,), "m", "ZMP, world frame"), Port("cop", (k, 3), "m", "centre of pressure per foot"),
                 Port("force", (k,), "N", "normal ground force per foot"), Port("inside", (), "1"),
                 Port("margin", (), "m", "distance inside the support polygon"),
                 Port("center", (3,), "m", "centre of the support polygon")]
        for i, foot in enumerate(feet):
            ports += [Port(f"{foot}.cop", (3,), "m", view_of=("cop", i)),
                      Port(f"{foot}.force", (), "N", view_of=("force", i))]
        return ports

    def setup(self, ctx: SetupContext) -> None:
        if not self.targets:
            raise fail(self.name, "targets", "name the feet: targets: [left_foot, right_foot]")
        self._link = MujocoLink(self.name, ctx.core)
        self._link.changed()
        self._resolve()

    def _resolve(self) -> None:
        link = self._link
        m = link.model
        d = mujoco.MjData(m)  # the model's reference pose: constant offsets come out the same in every state
        mujoco.mj_kinematics(m, d)
        feet = self._feet()
        self._foot_of = np.full(m.ngeom, -1, dtype=np.intp)
        sites, idx, depth = [], [], []
        for k, foot in enumerate(feet):
            geoms = link.subtree_geoms(foot)
            if not geoms:
                raise link.fail(f"body {foot!r} has no geoms that can collide: a ZMP sensor needs feet "
                                "that touch the ground")
            self._foot_of[geoms] = k
            site, sensors = self._ankle_sensor(foot)
            sites.append(site)
            idx.append(sensors)
            depth.append(_sole_depth(m, d, site, geoms))
        self._sites = np.array(sites, dtype=np.intp)
        self._bodies = np.array([link.lookup("body", f) for f in feet], dtype=np.intp)
        self._idx = np.stack(idx)  # (k, 6): force then torque
        self._depth = np.array(depth)
        self._mass = m.body_subtreemass[self._bodies].copy()

    def _ankle_sensor(self, foot: str) -> tuple[int, np.ndarray]:
        """The site of ``foot`` with native force and torque sensors, and their sensordata indices."""
        link, m = self._link, self._link.model
        body = link.lookup("body", foot)
        for s in range(m.nsite):
            if int(m.site_bodyid[s]) != body:
                continue
            found = {}
            for i in range(m.nsensor):
                if m.sensor_objtype[i] == int(mujoco.mjtObj.mjOBJ_SITE) and m.sensor_objid[i] == s:
                    found[int(m.sensor_type[i])] = int(m.sensor_adr[i])
            f, t = found.get(int(_SENS.mjSENS_FORCE)), found.get(int(_SENS.mjSENS_TORQUE))
            if f is not None and t is not None:
                return s, np.r_[f:f + 3, t:t + 3]
        raise link.fail(f"foot {foot!r} has no site with native force and torque sensors; the ZMP sensor "
                        "measures each foot's centre of pressure with them (add <force site=...>, <torque site=...>)")

    def start(self, t_ns: int) -> None:
        self.step(t_ns, 0)

    def step(self, t_ns: int, dt_ns: int) -> None:
        link = self._link
        if link.core._s is not link._seen:
            link.changed()
            self._resolve()
        m, d = link.model, link.data
        wrench = d.sensordata[self._idx]
        cop, fn = foot_pressure(d.site_xpos[self._sites], d.site_xmat[self._sites],
                                wrench[:, :3], wrench[:, 3:], self._depth, self._mass,
                                d.subtree_com[self._bodies], m.opt.gravity)
        if d.ncon:  # the foot each contact of the core's current list involves (-1 for none)
            contact = d.contact
            feet = self._foot_of[contact.geom].max(axis=1)
            touching = set(feet.tolist())
        else:
            touching = set()
        least = self._param_values["min_force"]
        loaded = [f > least and k in touching for k, f in enumerate(fn)]
        zmp = combined_pressure(cop, fn, loaded)
        values = list(zmp)  # every output in the order `outputs` declares them, written at once
        for point, on in zip(cop, loaded, strict=True):
            values += point if on else _NAN3
        values += [f if on else 0.0 for f, on in zip(fn, loaded, strict=True)]
        inside, margin, centre = 0.0, math.nan, _NAN3
        if any(loaded):  # then some contact involves a loaded foot: the support polygon has points
            keep = feet >= 0
            if not all(loaded):
                keep[keep] = np.array(loaded)[feet[keep]]
            points = contact.pos[keep]
            hull = convex_hull(points)
            distance = polygon_margin(zmp, hull)
            if math.isfinite(distance):
                margin = distance
                inside = 1.0 if distance >= self._param_values["min_margin"] and len(hull) >= 3 else 0.0
            heights = points[:, 2].tolist()
            centre = (*polygon_centre(hull), sum(heights) / len(heights))
        values += (inside, margin, *centre)
        self.out_flat[:] = values


_NAN3 = (math.nan, math.nan, math.nan)


def _sole_depth(m: mujoco.MjModel, d: mujoco.MjData, site: int, geoms: list[int]) -> float:
    """Distance from ``site`` down (along its -z) to the lowest point of the foot's geoms."""
    rot_s = d.site_xmat[site].reshape(3, 3)
    lowest = np.inf
    for g in geoms:
        rel = rot_s.T @ d.geom_xmat[g].reshape(3, 3)  # geom axes in the site frame
        z = float(rot_s[:, 2] @ (d.geom_xpos[g] - d.site_xpos[site]))
        size, kind = m.geom_size[g], int(m.geom_type[g])
        if kind == _BOX:
            extent = float(np.abs(rel[2]) @ size)
        elif kind == _SPHERE:
            extent = float(size[0])
        elif kind == _CAPSULE:
            extent = float(size[0] + abs(rel[2, 2]) * size[1])
        else:
            extent = float(m.geom_rbound[g])
        lowest = min(lowest, z - extent)
    return -lowest
