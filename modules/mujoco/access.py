"""Access to the MuJoCo core for modules that need native quantities (sensors, contacts, rules).

Most modules should talk to the physics core through the bus (``core.<joint>.q``, ``core.sensor.<name>``,
``core.<body>.pos``). Some need what the bus does not carry: MuJoCo's native sensors located by
site, the contact list, a body's geoms. They go through a `MujocoLink`, which reads the core's
model and data through its public view (`MujocoCore.mj`) and turns names into MuJoCo ids, so that the
rest of the module speaks names.

Contract of a link:

- ``MujocoLink(module, core, field)`` refuses a world without a core or with another engine, naming
  the module and the engine (``field`` is the scenario field the module's targets come from);
- ``model`` / ``data`` are those of the core's *current* compiled model (``core.mj``, a
  `MujocoView`): a scene edit (`make`, `make_joint`, `no_collision`) or a rollback across one switches
  the core to another compiled model, where ids differ. A module resolves its ids in a function of the
  model and calls ``link.changed()`` at the top of its step (one identity check) to re-resolve when
  needed;
- what a module reads is the physics as it is when the module steps: the state at the start of the
  tick when the module steps before the core (the usual case, when its outputs lead to the core's
  inputs: the same latency as a signal read from the core over the bus), the state after the core's
  step otherwise. The core keeps its data "after ``mj_step1``": positions, velocities, contacts and
  velocity-stage sensors are those of the current state; acceleration-stage sensors (force, torque,
  accelerometer, contact) are those computed during the core's last step;
- a link is copied with the module on `World.fork` (the copied module then reads the copied core);
- a module reads through it; the one exception is a rule that changes what physics cannot (breakout's
  vanishing blocks switch geoms off in the current model): it keeps what it changed in its own state
  and applies it again after every restore and every switch of the core's structure.
"""

from __future__ import annotations

import copy
import fnmatch
from collections.abc import Sequence
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.suggest import did_you_mean

if TYPE_CHECKING:
    from dynabrain.orchestrator.kernel.core import PhysicsCore

    from .compiled import MujocoView

_OBJ = mujoco.mjtObj
_HINGE, _SLIDE = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
_TRN_JOINT = (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT))


def contiguous(index: np.ndarray) -> slice | np.ndarray:
    """A slice for a run of consecutive indices (numpy reads and writes through a slice for less than
    through an index array), else the indices."""
    if len(index) and np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return slice(int(index[0]), int(index[0]) + len(index))
    return index


def fail(module: str, field: str, message: str) -> DynabrainError:
    """An error naming the module and the field (``targets``, ``params.sequence[2].pose``...)."""
    return DynabrainError(f"module {module!r} [{field}]: {message}")


class MujocoLink:
    """A module's read access to the MuJoCo core (see the module docstring for the contract)."""

    def __init__(self, module: str, core: PhysicsCore | None, field: str = "targets"):
        if core is None:
            raise fail(module, field, "needs a physics core, and this world has none")
        engine = core.ENGINE
        if engine != "mujoco":
            raise fail(module, field, f"needs the mujoco core; this world's core {core.name!r} is {engine!r}")
        self.module, self.field, self.core = module, field, core
        self.seen: MujocoView | None = None
        """The core's view the module last resolved its ids against (`changed` updates it)."""

    @property
    def model(self) -> mujoco.MjModel:
        return self.core.mj.model

    @property
    def data(self) -> mujoco.MjData:
        return self.core.mj.data

    def changed(self) -> bool:
        """True once after the core switched to another compiled model (and at the first call)."""
        view = self.core.mj
        if view is self.seen:
            return False
        self.seen = view
        return True

    def __deepcopy__(self, memo: dict) -> MujocoLink:
        twin = copy.copy(self)
        twin.core = copy.deepcopy(self.core, memo)
        twin.seen = None
        return twin

    # -- names --------------------------------------------------------------------------------------------
    def fail(self, message: str, field: str | None = None) -> DynabrainError:
        return fail(self.module, field or self.field, message)

    def names(self, kind: mujoco.mjtObj, count: int) -> list[str]:
        m = self.model
        return [mujoco.mj_id2name(m, kind, i) or "" for i in range(count)]

    def lookup(self, kind: str, name: str, field: str | None = None) -> int:
        """The id of a body, site, geom, joint or camera by name; an error naming the closest names."""
        objs = {"body": (_OBJ.mjOBJ_BODY, "nbody"), "site": (_OBJ.mjOBJ_SITE, "nsite"),
                "geom": (_OBJ.mjOBJ_GEOM, "ngeom"), "joint": (_OBJ.mjOBJ_JOINT, "njnt"),
                "camera": (_OBJ.mjOBJ_CAMERA, "ncam")}
        obj, count = objs[kind]
        i = mujoco.mj_name2id(self.model, obj, name)
        if i < 0:
            self._refuse_frozen(kind, name, field)
            known = [n for n in self.names(obj, getattr(self.model, count)) if n]
            listed = ", ".join(known[:10]) + (", ..." if len(known) > 10 else "") if known else "none"
            raise self.fail(f"no {kind} {name!r} in the model" + did_you_mean(name, known) + f"; {kind}s: {listed}",
                            field)
        return i

    def _refuse_frozen(self, kind: str, name: str, field: str | None) -> None:
        """A body or joint of the scene missing from the compiled model is frozen or absent: say so (a robot
        left out is animated, and keeps its joints: `mujoco.animate`)."""
        scene = self.core.bodies() if kind == "body" else self.core.joints() if kind == "joint" else []
        if name in scene:
            what = "a frozen or absent object" if self.core.absent else "a frozen object"
            raise self.fail(f"{kind} {name!r} belongs to {what} (not in the selection): select it "
                            "(make) before this module reads it", field)

    def native_sensor(self, site: str, kind: mujoco.mjtSensor, tag: str, field: str | None = None) -> np.ndarray:
        """Indices into ``data.sensordata`` of the model's native sensor of type ``kind`` on ``site``."""
        m = self.model
        sid = self.lookup("site", site, field)
        for s in range(m.nsensor):
            if m.sensor_type[s] == int(kind) and m.sensor_objtype[s] == int(_OBJ.mjOBJ_SITE) \
                    and m.sensor_objid[s] == sid:
                adr = int(m.sensor_adr[s])
                return np.arange(adr, adr + int(m.sensor_dim[s]))
        raise self.fail(f"site {site!r} has no native {tag} sensor; add <{tag} site=\"{site}\"/> to the model's "
                        "<sensor> section", field)

    def motor_joints(self) -> list[str]:
        """Hinge and slide joints driven by an actuator, in actuator order (the order of ``core.ctrl``)."""
        m = self.model
        out: list[str] = []
        for a in range(m.nu):
            if int(m.actuator_trntype[a]) in _TRN_JOINT:
                j = int(m.actuator_trnid[a, 0])
                if int(m.jnt_type[j]) in (_HINGE, _SLIDE):
                    name = m.joint(j).name
                    if name not in out:
                        out.append(name)
        return out

    def scalar_joints(self) -> list[str]:
        """Hinge and slide joints: those with a motor first (actuator order), then the others."""
        m = self.model
        motors = self.motor_joints()
        rest = [m.joint(j).name for j in range(m.njnt) if int(m.jnt_type[j]) in (_HINGE, _SLIDE)]
        return motors + [j for j in rest if j not in motors]

    def expand_joints(self, patterns: Sequence[str], field: str | None = None) -> list[str]:
        """Joint names (glob patterns allowed) in the order of `scalar_joints`; empty means the motor joints."""
        known = self.scalar_joints()
        if not patterns:
            if not self.motor_joints():
                raise self.fail("the model has no joint with a motor; name the joints in targets", field)
            return self.motor_joints()
        out: list[str] = []
        for pat in patterns:
            if any(ch in pat for ch in "*?["):
                hits = [j for j in known if fnmatch.fnmatchcase(j, pat)]
                if not hits:
                    raise self.fail(f"pattern {pat!r} matches no hinge or slide joint", field)
            elif pat in known:
                hits = [pat]
            else:
                self._refuse_frozen("joint", pat, field)
                listed = ", ".join(known[:10]) + (", ..." if len(known) > 10 else "")
                raise self.fail(f"no hinge or slide joint {pat!r}" + did_you_mean(pat, known) + f"; joints: {listed}",
                                field)
            out += [h for h in hits if h not in out]
        return out

    def joint_addresses(self, joints: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """(qpos addresses, dof addresses) of scalar joints."""
        m = self.model
        ids = [self.lookup("joint", j) for j in joints]
        return (np.array([m.jnt_qposadr[j] for j in ids], dtype=np.intp),
                np.array([m.jnt_dofadr[j] for j in ids], dtype=np.intp))

    def subtree_geoms(self, body: str, *, colliding: bool = True, field: str | None = None) -> list[int]:
        """Geoms of ``body`` and its descendants (only those that can collide, by default)."""
        m = self.model
        root = self.lookup("body", body, field)
        bodies = {root}
        for b in range(root + 1, m.nbody):
            if int(m.body_parentid[b]) in bodies:
                bodies.add(b)
        return [g for g in range(m.ngeom) if int(m.geom_bodyid[g]) in bodies
                and (not colliding or m.geom_contype[g] or m.geom_conaffinity[g])]
