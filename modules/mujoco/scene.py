"""Model building for the MuJoCo core: a structure (frozen objects, welds, collision exclusions) becomes a
compiled `mujoco.MjModel`, from the `mujoco.MjSpec` a SceneSpec or an MJCF file makes (`mujoco.spec_source`).

Structures. Every structure is compiled from a fresh spec (`SpecSource`). A frozen object loses its
joints, gets the pose it had when it was frozen baked into its bodies, and is fused into the world
(`mjs_fuseStatic`), so it costs no kinematics, no broad-phase box and no degrees of freedom; only its
geoms stay, as static world geoms that moving bodies still collide with. Bodies that something refers to
(a weld, an exclusion, a sensor) are not fused and stay as static bodies. An absent object (`make` with
``others="absent"``, `Edits.absent`) is not in the model at all: a primitive scene never builds its
bodies, a model file's are deleted with what acts only within them (`refs.leave_out`: refused, naming
it, when a sensor reads them or an actuator, equality, tendon, contact pair or exclusion, or a tracking
camera or light ties them to what stays), so it costs nothing, where a frozen object's static geoms
still cost MuJoCo per-geom kinematics and collision every step (195 frozen boxes: 16 us a step against
13 for 5 boxes alone). The core maps every compiled model back onto one fixed layout (the unedited
model's bodies, joints, actuators and sensors), by name, so that its block ports keep their shapes
across structures. What refers to a frozen object's joints (actuators, sensors, fixed tendons and
equalities) goes with them (`refs.prune`).

Robots. An object with joints that actuators drive (a robot) is not frozen but animated
(`FrozenObject.animated`, `mujoco.animate`): it keeps its joints, so the modules that read them keep
working, and follows its targets kinematically.

Contacts: a coefficient of restitution becomes contact parameters in `mujoco.restitution`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.core import Edits
from dynabrain.orchestrator.kernel.portable import state_type

from . import animate, refs
from .spec_source import GEOM_NAMES, VEL_PREFIX, SpecSource, fail, size_arena


# -- layout --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Layout:
    """The fixed layout of a core's ports, from the base model (row i of a body block is body i+1)."""

    bodies: tuple[str, ...]
    parents: tuple[str | None, ...]
    objects: tuple[str, ...]
    subtree: dict[str, tuple[str, ...]]
    body_joints: dict[str, tuple[str, ...]]
    free: frozenset[str]
    free_bodies: tuple[str, ...]
    """The bodies with a free joint, in body order: the rows of the ``body_wrench`` and
    ``body_velocity`` input blocks."""
    joints: tuple[str, ...]
    qjoints: tuple[str, ...]
    qunits: tuple[tuple[str, str], ...]
    actuators: tuple[str, ...]
    sensors: tuple[tuple[str, int, int], ...]
    nsensordata: int
    geoms: dict[str, tuple[dict, ...]] = field(repr=False)
    motor_joints: tuple[str, ...] = ()
    """Hinge and slide joints an actuator drives directly, in actuator order: the rows of the
    ``joint_target`` input, which animated robots follow (`mujoco.animate`)."""


def make_layout(model: mujoco.MjModel) -> Layout:
    names = tuple(model.body(i).name for i in range(1, model.nbody))
    parents = tuple(None if model.body_parentid[i] == 0 else model.body(int(model.body_parentid[i])).name
                    for i in range(1, model.nbody))
    subtree: dict[str, list[str]] = {n: [n] for n in names}
    for i in range(model.nbody - 1, 1, -1):  # children come after parents
        p = int(model.body_parentid[i])
        if p:
            subtree[names[p - 1]].extend(subtree[names[i - 1]])
    joints = tuple(model.joint(j).name for j in range(model.njnt))
    jnt_body, jnt_type = model.jnt_bodyid.tolist(), model.jnt_type.tolist()
    of_body: dict[int, list[str]] = {}
    for j, b in enumerate(jnt_body):
        of_body.setdefault(b, []).append(joints[j])
    body_joints = {n: tuple(of_body.get(i + 1, ())) for i, n in enumerate(names)}
    free_type = int(mujoco.mjtJoint.mjJNT_FREE)
    free = frozenset(names[jnt_body[j] - 1] for j in range(model.njnt) if jnt_type[j] == free_type)
    hinge, slide = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
    qj = [j for j in range(model.njnt) if jnt_type[j] in (hinge, slide)]
    qunits = tuple(("rad", "N*m") if jnt_type[j] == hinge else ("m", "N") for j in qj)
    sensors = tuple((model.sensor(s).name, int(model.sensor_dim[s]), int(model.sensor_adr[s]))
                    for s in range(model.nsensor) if not model.sensor(s).name.startswith(VEL_PREFIX))
    return Layout(bodies=names, parents=parents,
                  objects=tuple(n for n, p in zip(names, parents, strict=True) if p is None),
                  subtree={k: tuple(v) for k, v in subtree.items()}, body_joints=body_joints, free=free,
                  free_bodies=tuple(n for n in names if n in free),
                  joints=joints, qjoints=tuple(joints[j] for j in qj), qunits=qunits,
                  actuators=tuple(model.actuator(a).name for a in range(model.nu)), sensors=sensors,
                  nsensordata=sum(s[1] for s in sensors), geoms=_geom_info(model, names),
                  motor_joints=animate.motor_joints(model))


def _geom_info(model: mujoco.MjModel, names: tuple[str, ...]) -> dict[str, tuple[dict, ...]]:
    out: dict[str, list[dict]] = {n: [] for n in names}
    for g in range(model.ngeom):
        b = int(model.geom_bodyid[g])
        if b == 0:
            continue
        kind = GEOM_NAMES.get(int(model.geom_type[g]), "unknown")
        size = model.geom_size[g]
        scene_size = {"box": tuple(2 * size), "sphere": (size[0],), "capsule": (size[0], 2 * size[1]),
                      "cylinder": (size[0], 2 * size[1]),
                      "plane": tuple(size[:2]) if size[0] > 0 else ()}.get(kind, tuple(size))
        info = {"name": model.geom(g).name, "type": kind, "size": tuple(float(x) for x in scene_size),
                "rgba": tuple(float(x) for x in model.geom_rgba[g]),
                "pos": tuple(float(x) for x in model.geom_pos[g]),
                "quat": tuple(float(x) for x in model.geom_quat[g])}
        if kind == "mesh":
            info["mesh"] = model.mesh(int(model.geom_dataid[g])).name
        out[names[b - 1]].append(info)
    return {k: tuple(v) for k, v in out.items()}


# -- structures ------------------------------------------------------------------------------------------
@state_type
class FrozenBody(NamedTuple):
    """Where one body of a frozen object stood when it froze."""

    name: str
    in_parent: tuple[float, ...] | None
    """Its pose in its parent's frame (x, y, z, qw, qx, qy, qz), baked into the model; None for a body
    without joints of its own (it keeps the pose the model gives it)."""
    in_world: tuple[float, ...]
    """Its pose in the world frame (x, y, z, qw, qx, qy, qz): the outputs of a body fused into the world."""


@state_type
class FrozenObject(NamedTuple):
    """The MuJoCo core's entry of one frozen object in `Edits.frozen` (`MujocoCore._freeze_entry`)."""

    object: str
    bodies: tuple[FrozenBody, ...]
    """Every body of the object's subtree."""
    joints: tuple[tuple[str, tuple[float, ...]], ...]
    """(joint, its qpos values) for every joint of the subtree: its outputs while frozen, and where it
    starts again when the object is selected."""
    animated: bool = False
    """A robot (joints that actuators drive): animated, not frozen (`mujoco.animate`): it keeps its joints,
    which hold these values or follow their targets."""


def build_structure(core: str, source: SpecSource, edits: Edits) -> tuple[mujoco.MjModel, tuple[str, ...]]:
    """Compile the structure ``edits``; return it and its moving bodies."""
    absent = set(edits.absent)
    spec, removed = source.spec({b.name: b.in_parent for entry in edits.frozen
                                 if entry.object not in absent and not entry.animated
                                 for b in entry.bodies}, edits.scene_key(),
                                {e.object: tuple(b.name for b in e.bodies) for e in edits.frozen if e.object in absent})
    size_arena(spec, source.size(edits))
    if removed:
        refs.prune(core, spec, removed)
    gone = {b.name for e in edits.frozen if e.object in absent for b in e.bodies}
    welds = tuple(w for w in edits.welds if w.a not in gone)  # (both sides are absent, or neither: `make`)
    animate.make_kinematic(spec, [e for e in edits.frozen if e.animated and e.object not in absent])  # (before the
    anchors = _made_joints(spec, welds)  # joints made at run time: those it holds stay)
    groups = tuple(g for g in (tuple(n for n in grp if n not in gone) for grp in edits.groups) if len(g) > 1)
    for pair in _exclusions(spec, groups):
        spec.add_exclude(bodyname1=pair[0], bodyname2=pair[1])
    movers = _moving_bodies(spec)
    for kind, tag in ((mujoco.mjtSensor.mjSENS_FRAMELINVEL, "lin"),
                      (mujoco.mjtSensor.mjSENS_FRAMEANGVEL, "ang")):
        for b in movers:  # all linear velocities first, then all angular ones: two (n, 3) blocks
            spec.add_sensor(name=f"{VEL_PREFIX}{tag}_{b}", type=kind, objtype=mujoco.mjtObj.mjOBJ_XBODY,
                            objname=b)
    try:
        if edits.frozen:
            spec.fuse_static()
        model = spec.compile()
        carriages = [w for w in edits.welds if w.kind == "slider"]
        if carriages:  # each carriage weighs a hundredth of the body sliding on it: compile again with that
            for w in carriages:
                mass = CARRIAGE_SHARE * float(model.body_subtreemass[model.body(w.b).id]) or CARRIAGE_SHARE
                carriage = spec.body(CARRIAGE + w.name)
                carriage.mass, carriage.inertia = mass, [mass * CARRIAGE_RADIUS ** 2] * 3
            model = spec.compile()
    except Exception as exc:
        what = ", ".join(e.object for e in edits.frozen)
        raise fail(core, f"cannot build the structure (frozen: {what or 'none'}): {exc}") from None
    for name, anchor_b in anchors:  # MuJoCo computes a connect's second anchor from the model's qpos0: set it
        model.eq_data[model.equality(name).id, 3:6] = anchor_b
    return model, movers


CARRIAGE = "__dynabrain_carriage_"
"""Name prefix of the carriage body of a slider made at run time."""
CARRIAGE_SHARE = 0.01
"""A slider's carriage weighs this share of the body that slides on it (a body has to have a mass)."""
CARRIAGE_RADIUS = 0.01
"""The carriage's radius of gyration (m): its inertia is its mass times this squared."""
HINGE_HALF = 0.05
"""A hinge holds two points of its axis together, this far (m) on either side of the anchor."""
SECOND = "__dynabrain_2"
"""Name suffix of a hinge's second point constraint."""


def made_equalities(weld) -> tuple[str, ...]:
    """The names of the MuJoCo equalities that make a joint made at run time (`Weld`)."""
    return (weld.name, weld.name + SECOND) if weld.kind == "hinge" else (weld.name,)


def _made_joints(spec: mujoco.MjSpec, welds: tuple) -> list[tuple[str, np.ndarray]]:
    """Add the joints made at run time: a weld is a weld equality; a ball holds its anchor together (a
    connect equality), a hinge two points of its axis; a slider is a carriage body on a slide joint in
    body a, body b welded to it. Returns each connect's name and its anchor in body b (to set once
    compiled)."""
    fixes = []
    weld_type, connect, body = mujoco.mjtEq.mjEQ_WELD, mujoco.mjtEq.mjEQ_CONNECT, mujoco.mjtObj.mjOBJ_BODY
    for w in welds:
        if w.kind == "weld":
            spec.add_equality(type=weld_type, objtype=body, name=w.name, name1=w.a, name2=w.b,
                              data=np.asarray(w.data, dtype=np.float64))
            continue
        f = w.data
        if w.kind == "slider":
            carriage = spec.body(w.a).add_body(name=CARRIAGE + w.name, pos=list(f.pos_a), quat=list(f.quat_a))
            carriage.mass, carriage.inertia, carriage.explicitinertial = CARRIAGE_SHARE, [1e-6] * 3, True
            carriage.add_joint(name=CARRIAGE + w.name, type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0.0, 0.0, 1.0])
            inv = _inverse(f.pos_b, f.quat_b)  # body b in the joint frame
            spec.add_equality(type=weld_type, objtype=body, name=w.name, name1=CARRIAGE + w.name, name2=w.b,
                              data=np.array([0.0, 0.0, 0.0, *inv, 1.0, 0.0]))
            continue
        points = [(0.0, 0.0, 0.0)] if w.kind == "ball" else [(0.0, 0.0, -HINGE_HALF), (0.0, 0.0, HINGE_HALF)]
        for name, point in zip(made_equalities(w), points, strict=True):
            at_a, at_b = (np.asarray(pos) + _rotate(quat, point) for pos, quat in ((f.pos_a, f.quat_a),
                                                                                   (f.pos_b, f.quat_b)))
            spec.add_equality(type=connect, objtype=body, name=name, name1=w.a, name2=w.b,
                              data=np.array([*at_a, *at_b, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
            fixes.append((name, at_b))
    return fixes


def _rotate(quat, v) -> np.ndarray:
    out = np.empty(3)
    mujoco.mju_rotVecQuat(out, np.asarray(v, dtype=np.float64), np.asarray(quat, dtype=np.float64))
    return out


def _inverse(pos, quat) -> tuple[float, ...]:
    """The pose (pos, quat) inverse of ``pos``, ``quat``."""
    neg = np.empty(4)
    mujoco.mju_negQuat(neg, np.asarray(quat, dtype=np.float64))
    return (*map(float, -_rotate(neg, pos)), *map(float, neg))


def _exclusions(spec: mujoco.MjSpec, groups: tuple) -> list[tuple[str, str]]:
    def subtree(name: str) -> list[str]:
        out, stack = [], [spec.body(name)]
        while stack:
            b = stack.pop()
            out.append(b.name)
            stack.extend(b.bodies)
        return out

    pairs: dict[tuple[str, str], None] = {}
    for group in groups:
        trees = [subtree(n) for n in group]
        for i, ta in enumerate(trees):
            for tb in trees[i + 1:]:
                for a in ta:
                    for b in tb:
                        if a != b:
                            pairs[(a, b) if a < b else (b, a)] = None
    return list(pairs)


def _moving_bodies(spec: mujoco.MjSpec) -> tuple[str, ...]:
    out: list[str] = []
    stack = [(b, False) for b in reversed(spec.worldbody.bodies)]
    while stack:
        body, moving = stack.pop()
        moving = moving or bool(body.joints) or bool(body.mocap)
        if moving and not body.name.startswith(CARRIAGE):  # (a carriage has no port)
            out.append(body.name)
        stack.extend((c, moving) for c in reversed(body.bodies))
    return tuple(out)


def relative_pose(model: mujoco.MjModel, data: mujoco.MjData, body: int) -> tuple[float, ...]:
    """Pose (pos, quat) of ``body`` in its parent's frame, now."""
    parent = int(model.body_parentid[body])
    neg, quat, pos = np.empty(4), np.empty(4), np.empty(3)
    mujoco.mju_negQuat(neg, data.xquat[parent])
    mujoco.mju_mulQuat(quat, neg, data.xquat[body])
    mujoco.mju_rotVecQuat(pos, data.xpos[body] - data.xpos[parent], neg)
    return (*map(float, pos), *map(float, quat))


def weld_data(pos_a, quat_a, pos_b, quat_b) -> tuple[float, ...]:
    """Equality data welding body b to body a at their current relative pose."""
    neg, quat, pos = np.empty(4), np.empty(4), np.empty(3)
    mujoco.mju_negQuat(neg, quat_a)
    mujoco.mju_mulQuat(quat, neg, quat_b)
    mujoco.mju_rotVecQuat(pos, np.asarray(pos_b) - pos_a, neg)
    return (0.0, 0.0, 0.0, *map(float, pos), *map(float, quat), 1.0, 0.0)


# -- helpers of the core's structures ------------------------------------------------------------------
class JointSlice(NamedTuple):
    """Where a joint's values lie in MuJoCo's ``qpos`` and ``qvel`` arrays."""

    qpos_adr: int
    nq: int
    """Its number of position values (7 free, 4 ball, 1 hinge or slide)."""
    dof_adr: int
    nv: int
    """Its number of degrees of freedom (6 free, 3 ball, 1 hinge or slide)."""


def joint_slice(model: mujoco.MjModel, j: int) -> JointSlice:
    """Where the values of joint ``j`` lie in ``qpos`` and ``qvel``."""
    size = {0: (7, 6), 1: (4, 3)}.get(int(model.jnt_type[j]), (1, 1))
    return JointSlice(int(model.jnt_qposadr[j]), size[0], int(model.jnt_dofadr[j]), size[1])


def pose_index(pairs: list[tuple[int, int]]) -> tuple:
    """Flat indices of (layout row, body id) pairs into position (3) and quaternion (4) blocks."""
    rows, ids = [p[0] for p in pairs], [p[1] for p in pairs]
    return flat_index(rows, 3), flat_index(ids, 3), flat_index(rows, 4), flat_index(ids, 4)


def flat_index(rows: list[int], width: int) -> slice | np.ndarray:
    """Flat positions of ``rows`` of a C-ordered (n, width) array: a slice when they are contiguous."""
    if rows and rows == list(range(rows[0], rows[0] + len(rows))):
        return slice(rows[0] * width, (rows[0] + len(rows)) * width)
    return (np.asarray(rows, dtype=int).reshape(-1, 1) * width + np.arange(width)).reshape(-1)


def carry_over(old, new) -> None:
    """Start compiled scene ``new`` from the state of compiled scene ``old`` (the core's
    `CompiledScene`s): joints, actuators and equalities by name; joints that were frozen start at
    their frozen value, at rest."""
    m, d = new.model, new.data
    mujoco.mj_resetData(m, d)
    d.time = old.data.time
    frozen = {j: v for entry in old.edits.frozen for j, v in entry.joints}
    od = old.data
    for name, (qa, nq, da, nv) in new.joint_slices.items():
        if name in old.joint_slices:
            oqa, _, oda, _ = old.joint_slices[name]
            d.qpos[qa:qa + nq] = od.qpos[oqa:oqa + nq]
            d.qvel[da:da + nv] = od.qvel[oda:oda + nv]
            d.qacc_warmstart[da:da + nv] = od.qacc_warmstart[oda:oda + nv]
        elif name in frozen:
            d.qpos[qa:qa + nq] = frozen[name]
    acts = {old.model.actuator(a).name: a for a in range(old.model.nu)}
    for a in range(m.nu):
        k = acts.get(m.actuator(a).name)
        if k is not None:
            d.ctrl[a] = od.ctrl[k]
            n = int(m.actuator_actnum[a])
            if n:
                d.act[m.actuator_actadr[a]:m.actuator_actadr[a] + n] = \
                    od.act[old.model.actuator_actadr[k]:old.model.actuator_actadr[k] + n]
    for e in range(m.neq):
        name = m.equality(e).name
        k = mujoco.mj_name2id(old.model, mujoco.mjtObj.mjOBJ_EQUALITY, name) if name else -1
        if k >= 0:
            d.eq_active[e] = od.eq_active[k]
    for b in np.flatnonzero(m.body_mocapid >= 0):
        k = old.body_id.get(m.body(int(b)).name)
        if k is not None and old.model.body_mocapid[k] >= 0:
            new_id, old_id = m.body_mocapid[b], old.model.body_mocapid[k]
            d.mocap_pos[new_id], d.mocap_quat[new_id] = od.mocap_pos[old_id], od.mocap_quat[old_id]
