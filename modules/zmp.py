"""The ZMP sensor: centre of pressure of each foot and of both, and whether it lies in the support polygon.

Everything comes from the contact forces, read through MuJoCo's native contact sensor: each foot
needs one in the model, on the foot's body or subtree, reporting at least ``found``, ``force`` and
``pos`` of each contact (the error says what to add when it is missing)::

    <contact name="l_sole" subtree1="l_foot" data="found force pos" num="8"/>

A foot's centre of pressure is the mean of its contact points weighted by their normal forces (exact
for a flat sole on a flat floor, tilted or not), and its normal force their sum. The ZMP of the feet
together is the same mean over all loaded feet. A foot is loaded when its contacts carry at least
``min_force`` in all. The support polygon is the convex hull of the loaded feet's contact points that
carry a force. (MuJoCo's ``reduce="netforce"`` is refused: its point is the mean weighted by the
whole force, friction included, which is not the centre of pressure.)

The sensor's values are those of the core's last step (an acceleration-stage sensor, see
`modules.mujoco.access`), and the core restores them on rollback. A foot with more contacts than its
sensor's ``num`` slots would give a wrong centre of pressure: the step then fails, naming the sensor.

Targets: the feet (bodies). Outputs:

==============  =======  ====  ======================================================================
port            shape    unit  meaning
==============  =======  ====  ======================================================================
``zmp``         (3,)     m     ZMP (centre of pressure of the loaded feet), world frame; NaN airborne
``cop``         (k, 3)   m     each foot's centre of pressure (NaN when not loaded); ``<foot>.cop``
``force``       (k,)     N     each foot's normal ground force (0 when not loaded); ``<foot>.force``
``inside``      ()       1     1 when the ZMP is at least ``min_margin`` inside the support polygon, else 0
``margin``      ()       m     signed distance from the ZMP to the polygon's edge (positive inside)
``center``      (3,)     m     centre of the support polygon (mean of its vertices)
==============  =======  ====  ======================================================================
"""

from __future__ import annotations

import struct
from typing import Any

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.module import Capabilities, Module, Param, Port, SetupContext

from .mujoco.access import MujocoLink, fail
from .support import ContactOverflowError, feet_support

_CONTACT = int(mujoco.mjtSensor.mjSENS_CONTACT)
_FOOT_OBJECTS = (int(mujoco.mjtObj.mjOBJ_XBODY), int(mujoco.mjtObj.mjOBJ_BODY))  # subtree1=, body1=
_FIELDS = ("found", "force", "torque", "dist", "pos", "normal", "tangent", "linvel", "angvel")  # data= bits
_SIZES = (1, 3, 3, 1, 3, 3, 3, 3, 3)
_NEEDED = ("found", "force", "pos")
_NETFORCE = 3  # reduce="netforce"


class ZmpSensor(Module):
    """ZMP and support polygon of a set of feet (see the module docstring)."""

    CAPABILITIES = Capabilities(finite_outputs=False)  # NaN: a foot (or both) off the ground

    PARAMS = (
        Param("min_force", 1.0, unit="N", runtime=True,
              doc="a foot is loaded when its contacts carry at least this normal force in all"),
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
        self._write: tuple | None = None  # (pack_into, the outputs' memoryview), made by `bind`

    def _resolve(self) -> None:
        """Each foot's contact sensor, as indices into sensordata: one gather reads every value a step
        needs, laid out as [found of each foot] + [normal forces of each foot] + [points of each foot]."""
        link = self._link
        found, normal, points, self._sensors = [], [], [], []
        for foot in self._feet():
            if not link.subtree_geoms(foot):
                raise link.fail(f"body {foot!r} has no geoms that can collide: a ZMP sensor needs feet "
                                "that touch the ground")
            name, adr, slot, num, offset = self._contact_sensor(foot)
            self._sensors.append((foot, name, num))
            found.append(adr + offset["found"])
            normal += [adr + j * slot + offset["force"] for j in range(num)]  # the force's first component
            points += [adr + j * slot + offset["pos"] + i for j in range(num) for i in range(3)]
        self._index = np.array(found + normal + points, dtype=np.intp)
        self._nums = [num for _foot, _name, num in self._sensors]
        self._sensordata = link.data.sensordata

    def _contact_sensor(self, foot: str) -> tuple[str, int, int, int, dict[str, int]]:
        """The foot's native contact sensor: (name, sensordata address, values per contact, contacts it
        holds, offset of each data field within a contact)."""
        link, m = self._link, self._link.model
        body = link.lookup("body", foot)
        add = (f'add <contact name="{foot}_contacts" subtree1="{foot}" data="found force pos" num="8"/> '
               "to the model's <sensor>")
        unfit = None
        for s in range(m.nsensor):
            if int(m.sensor_type[s]) != _CONTACT or int(m.sensor_objtype[s]) not in _FOOT_OBJECTS \
                    or int(m.sensor_objid[s]) != body:
                continue
            bits, reduce, num = (int(v) for v in m.sensor_intprm[s][:3])
            fields = [f for i, f in enumerate(_FIELDS) if bits >> i & 1]
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SENSOR, s) or f"#{s}"
            missing = [f for f in _NEEDED if f not in fields]
            if missing:
                unfit = (f"its contact sensor {name!r} does not report {', '.join(missing)}: "
                         'give it data="found force pos"')
                continue
            if reduce == _NETFORCE:
                unfit = (f"its contact sensor {name!r} sums the contacts (reduce=\"netforce\"), whose point is not "
                         "the centre of pressure: the ZMP needs each contact (leave reduce out)")
                continue
            offset, at = {}, 0
            for f in fields:
                offset[f] = at
                at += _SIZES[_FIELDS.index(f)]
            return name, int(m.sensor_adr[s]), at, num, offset
        raise link.fail(f"foot {foot!r}: {unfit}" if unfit else
                        f"foot {foot!r} has no contact sensor; the ZMP sensor measures the contact forces with "
                        f"one: {add}")

    def start(self, t_ns: int) -> None:
        self.step(t_ns, 0)

    def bind(self) -> None:
        out = self.out_flat
        self._write = (struct.Struct(f"={out.size}d").pack_into, memoryview(out)) if out.size else None

    def __getstate__(self) -> dict[str, Any]:
        """For a fork's deep copy: a memoryview does not copy; the copy makes its own when it is bound."""
        return {**self.__dict__, "_write": None}

    def step(self, t_ns: int, dt_ns: int) -> None:
        link = self._link
        if link.core.mj is not link.seen:  # the core switched model: find the ids again
            link.changed()
            self._resolve()
        values = self.support(self._sensordata[self._index].tolist())
        write = self._write  # every output, in the order `outputs` declares them, packed into the bus's
        if write is None:    # bytes (0.19 us, against 0.46 to assign the list to the array)
            self.out_flat[:] = values
        else:
            write[0](write[1], 0, *values)

    def support(self, values: list[float]) -> list[float]:
        """The outputs, flat, from the contact sensors' values (those at ``_index`` in sensordata, as a
        list): what a step writes (a lockstep batch reads every branch's values at once, then this)."""
        p = self.params
        try:
            return feet_support(values, self._nums, p["min_force"], p["min_margin"])
        except ContactOverflowError as exc:
            foot, name, num = self._sensors[exc.foot]
            raise RuntimeError(f"foot {foot!r}: its contact sensor {name!r} found {exc.found} contacts and holds "
                               f"{num} (num={num}): raise num, or the centre of pressure misses contacts") from None
