"""Model building for the MuJoCo core: a SceneSpec or an MJCF file becomes an `mujoco.MjSpec`, a
structure (frozen objects, welds, collision exclusions) becomes a compiled `mujoco.MjModel`.

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

import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.core import FLEX_SHAPES, SHAPES, BodySpec, Edits, SceneSpec, scene_bodies
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.portable import state_type
from dynabrain.orchestrator.kernel.suggest import did_you_mean

from . import animate, options, refs

ENGINE = "mujoco"
_GEOMS = {"plane": mujoco.mjtGeom.mjGEOM_PLANE, "box": mujoco.mjtGeom.mjGEOM_BOX,
          "sphere": mujoco.mjtGeom.mjGEOM_SPHERE, "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
          "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER, "mesh": mujoco.mjtGeom.mjGEOM_MESH}
_GEOM_NAMES = {int(v): k for k, v in _GEOMS.items()} | {
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
    int(mujoco.mjtGeom.mjGEOM_HFIELD): "hfield", int(mujoco.mjtGeom.mjGEOM_SDF): "sdf"}
MESH_PREFIX = "__dynabrain_mesh_"
"""Name prefix of the mesh asset of a ``mesh`` body (its geom is named as the body)."""
_JOINTS = {"hinge": mujoco.mjtJoint.mjJNT_HINGE, "slide": mujoco.mjtJoint.mjJNT_SLIDE}
VEL_PREFIX = "__dynabrain_vel_"
"""Name prefix of the velocity sensors the core adds to read body velocities in one step."""


def fail(core: str, message: str) -> DynabrainError:
    return DynabrainError(f"{ENGINE} core {core!r}: {message}")


# -- size: how many bodies, and MuJoCo's memory for a step -------------------------------------------------
MAX_BODIES = 65_535
"""The most bodies MuJoCo can simulate: its broad phase (sweep and prune) numbers bodies in 16 bits and
fails above this. A scene with more is refused when the core is made."""
ARENA_BASE = 64 * 2**20
"""Bytes of MuJoCo's arena (contacts, constraints, the step's scratch) every model gets (`arena_bytes`)."""
ARENA_PER_DOF = 40 * 1024
"""... and per degree of freedom or equality: 1000 boxes piled 10 x 10 x 10 (one island of 6000 dofs,
14,000 contacts) use 20 KiB a dof at most."""
ARENA_PER_GEOM = 16 * 1024
"""... and per geom: its contacts (a box resting on the floor has 4, about 2 KiB with their constraints)."""


class ModelSize(NamedTuple):
    """What sizes MuJoCo's memory for a step: bodies, geoms, degrees of freedom, equalities."""

    nbody: int = 0
    ngeom: int = 0
    nv: int = 0
    neq: int = 0

    def __add__(self, other):  # type: ignore[override]
        return ModelSize(*(a + b for a, b in zip(self, other, strict=True)))


_DOFS = {"free": 6, "hinge": 1, "slide": 1, "fixed": 0}


def _bodies_size(bodies: Sequence[BodySpec]) -> ModelSize:
    nv = sum(0 if b.shape == "plane" else
             _DOFS.get(b.joint.kind if b.joint is not None else ("free" if b.parent is None else "fixed"), 6)
             for b in bodies)
    return ModelSize(nbody=len(bodies), ngeom=len(bodies), nv=nv)


def _spec_size(spec: mujoco.MjSpec) -> ModelSize:
    dofs = {mujoco.mjtJoint.mjJNT_FREE: 6, mujoco.mjtJoint.mjJNT_BALL: 3}
    return ModelSize(nbody=len(spec.bodies) - 1, ngeom=len(spec.geoms),
                     nv=sum(dofs.get(j.type, 1) for j in spec.joints), neq=len(spec.equalities))


def _check_bodies(core: str, n: int) -> None:
    if n > MAX_BODIES:
        raise fail(core, f"{n} bodies: MuJoCo simulates at most {MAX_BODIES} (its broad phase numbers bodies "
                   "in 16 bits)")


def arena_bytes(size: ModelSize) -> int:
    """MuJoCo's memory for one step of a model of ``size`` (its ``<size memory>``): what its broad phase
    takes, two int lists of every pair of bodies (4 n^2 bytes, freed before the constraints are made; only
    the pages it writes are ever touched), and room for the contacts and constraints linear in the model:
    `ARENA_BASE`, `ARENA_PER_DOF`, `ARENA_PER_GEOM`."""
    pairs = 4 * (size.nbody + 1) ** 2
    return pairs + ARENA_BASE + ARENA_PER_DOF * (size.nv + size.neq) + ARENA_PER_GEOM * size.ngeom


def _size_arena(spec: mujoco.MjSpec, size: ModelSize) -> None:
    """Give the spec `arena_bytes` of memory where MuJoCo's own rule would give more. MuJoCo's rule, for a
    model that sets none, grows with the square of the degrees of freedom (at least 40 (500 + nv + neq)^2
    bytes: 1.7 GB for 1000 free boxes, 146 GB for 10,000, which no machine allocates); a model file's own
    ``<size memory>`` (or ``nstack``) is kept."""
    if spec.memory != -1 or spec.nstack != -1:
        return
    ours = arena_bytes(size)
    if ours < 40 * (500 + size.nv + size.neq) ** 2:
        spec.memory = ours


# -- specs ----------------------------------------------------------------------------------------------
_BASE_LOCK = threading.Lock()


class SpecSource:
    """Makes the spec of a structure. A primitive scene is rebuilt from its bodies, frozen bodies
    without their joints (fast); an MJCF model is copied and the frozen joints are deleted (deleting
    is slow in MuJoCo, about 0.4 ms a joint, so only done for model files).

    Never changed once made (`spec` edits a copy of the base), so a core's forks share it."""

    def __init__(self, core: str, scene: SceneSpec, scenario_dir: str | None):
        if scene.model and scene.bodies:
            raise fail(core, "a scene has either a model file or bodies, not both")
        self.core, self.scene = core, scene
        path = _model_path(core, scene.model, scenario_dir) if scene.model else None
        own = options.declared(path) if path else frozenset()  # the options the file sets itself: kept
        self.base = _finish(core, _spec_from_file(core, path), scene, own=own) if path else None
        self.geom_body = _geom_owners(self.base) if self.base is not None else {}
        """Geom name -> the body it belongs to, for the model file's geoms (a primitive's geom is
        named as its body)."""
        self.timestep_s = options.own_timestep(self.base, scene.options or {}, own)
        """The timestep the scene asks for (its options', or a model file's own), or None (`mujoco.options`)."""
        self.base_size = _spec_size(self.base) if self.base is not None else ModelSize()
        """The model file's size (nothing for a primitive scene: its bodies say)."""
        _check_bodies(core, self.base_size.nbody + len(scene.bodies))
        self._first: mujoco.MjSpec | None = None
        """The spec of the scene as it is, made to check the scene at construction and kept for the
        first structure that asks for it (building a spec costs MuJoCo time quadratic in the bodies)."""
        if self.base is None:
            self._first = self.spec({})[0]  # check the scene now: errors belong to construction

    def bodies(self, scene_key: tuple = ((), ())) -> tuple[BodySpec, ...]:
        """The primitives of the scene with the bodies added and removed of ``scene_key``."""
        return scene_bodies(self.scene, scene_key)

    def spec(self, bake: dict[str, tuple | None], scene_key: tuple = ((), ()),
             absent: dict[str, tuple[str, ...]] | None = None) -> tuple[mujoco.MjSpec, set[str]]:
        """A fresh spec with the bodies of ``bake`` frozen (pose in parent, or None: keep), and the
        names of the joints that froze; with the bodies added and removed of ``scene_key``, and without
        the absent objects of ``absent`` (object -> its bodies): a primitive scene never builds them, a
        model file's are deleted (`refs.leave_out`)."""
        gone = {b for bodies in (absent or {}).values() for b in bodies}
        if self.base is None:
            first, self._first = self._first, None
            if first is not None and not bake and scene_key == ((), ()) and not gone:
                return first, set()
            bodies = self.bodies(scene_key)
            if gone:
                bodies = tuple(b for b in bodies if b.name not in gone)
            _check_bodies(self.core, len(bodies))
            spec = _finish(self.core, _spec_from_bodies(self.core, bodies, bake), self.scene, named=True)
            removed: set[str] = set()  # frozen bodies were built without joints
        else:
            _check_bodies(self.core, self.base_size.nbody + len(scene_key[0]))
            with _BASE_LOCK:  # forks share the base and may compile in threads
                spec = self.base.copy()
            for b in scene_key[0]:  # bodies added at run time (only those: model bodies are not removed)
                if b.name in {x.name for x in spec.bodies}:
                    raise fail(self.core, f"{_where(b)}a body of that name exists already")
                _add_body(self.core, spec, spec.worldbody, b, b.name in bake, bake.get(b.name),
                          degree=bool(spec.compiler.degree))
            removed = refs.leave_out(self.core, spec, absent) if absent else set()
            for name, rel in bake.items():
                removed |= _bake(spec.body(name), rel, spec)
        for name in bake:
            spec.body(name).fuse = 1
        return spec, removed

    def size(self, edits: Edits) -> ModelSize:
        """An upper bound of the size of the model of ``edits`` (frozen bodies counted as moving)."""
        if self.base is None:
            size = _bodies_size(self.bodies(edits.scene_key()))
        else:
            size = self.base_size + _bodies_size(edits.scene_key()[0])
        sliders = sum(w.kind == "slider" for w in edits.welds)  # a carriage body on a slide joint each
        return size + ModelSize(nbody=sliders, nv=sliders, neq=2 * len(edits.welds))


def _finish(core: str, spec: mujoco.MjSpec, scene: SceneSpec, *, named: bool = False,
            own: frozenset[str] = frozenset()) -> mujoco.MjSpec:
    """Options (``own``: those a model file sets itself, `mujoco.options.declared`), names and no fusing;
    ``named``: the spec names everything already (a primitive scene: MuJoCo's lists of every joint and
    geom cost time quadratic in their number)."""
    try:
        options.apply(spec, scene.options or {}, own=own)
    except ValueError as exc:
        raise fail(core, f"scene, field options: {exc}") from None
    if not named:
        _name_everything(spec)
        for body in spec.bodies:
            body.fuse = 0  # only frozen bodies are fused (see build_structure)
    spec.compiler.fusestatic = False
    return spec


def _model_path(core: str, path: str, scenario_dir: str | None) -> str:
    full = path if os.path.isabs(path) or scenario_dir is None else os.path.join(scenario_dir, path)
    if not os.path.isfile(full):
        raise fail(core, f"model file {full!r} not found")
    return full


def _spec_from_file(core: str, full: str) -> mujoco.MjSpec:
    try:
        return mujoco.MjSpec.from_file(full)
    except Exception as exc:  # mujoco raises ValueError with the parser's message
        kind = "URDF" if full.lower().endswith(".urdf") else "MJCF"
        raise fail(core, f"cannot read {kind} model file {full!r}: {exc}") from None


def _spec_from_bodies(core: str, bodies: Sequence[BodySpec], bake: dict) -> mujoco.MjSpec:
    spec = mujoco.MjSpec()
    spec.compiler.degree = False  # a SceneSpec is in radians (MjSpec, like MJCF, defaults to degrees)
    names = [b.name for b in bodies]
    by_name = {b.name: b for b in bodies}
    if len(by_name) != len(bodies):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise fail(core, f"body names must be unique; repeated: {', '.join(dup)}")
    made: dict[str, mujoco.MjsBody] = {}

    def make(b: BodySpec, chain: tuple[str, ...]) -> mujoco.MjsBody:
        if b.name in made:
            return made[b.name]
        if b.parent is not None and b.parent not in by_name:
            raise fail(core, f"{_where(b)}parent {b.parent!r} is not a body" + did_you_mean(b.parent, by_name))
        if b.parent in chain:
            raise fail(core, f"{_where(b)}parent cycle: {' -> '.join((*chain, b.name))}")
        parent = spec.worldbody if b.parent is None else make(by_name[b.parent], (*chain, b.name))
        made[b.name] = _add_body(core, spec, parent, b, b.name in bake, bake.get(b.name))
        return made[b.name]

    for b in bodies:
        make(b, ())
    return spec


def _where(b: BodySpec) -> str:
    return f"body {b.name!r}" + (f" (line {b.line})" if b.line else "") + ": "


def _add_body(core: str, spec: mujoco.MjSpec, parent: mujoco.MjsBody, b: BodySpec, frozen: bool,
              rel: tuple | None, *, degree: bool = False) -> mujoco.MjsBody:
    if b.shape in FLEX_SHAPES:
        raise fail(core, f"{_where(b)}a flexible body (shape {b.shape!r}) is not supported by the mujoco core; "
                   "flexible bodies need core: exudyn")
    if b.shape not in _GEOMS:
        raise fail(core, f"{_where(b)}shape {b.shape!r} is not supported by the mujoco core "
                   f"(supported: {', '.join(SHAPES)})" + did_you_mean(b.shape, _GEOMS))
    pos, quat = (rel[:3], rel[3:]) if rel is not None else (b.pos, b.quat)
    body = parent.add_body(name=b.name, pos=list(pos), quat=list(quat))
    body.fuse = 0  # only frozen bodies are fused (see build_structure)
    geom = body.add_geom(name=b.name, type=_GEOMS[b.shape], size=_geom_size(core, b),
                         rgba=list(b.color))
    if b.shape == "mesh":
        geom.meshname = _add_mesh(spec, b)
    if b.mass is not None:
        if b.mass <= 0:
            raise fail(core, f"{_where(b)}mass must be positive, got {b.mass}")
        geom.mass = float(b.mass)
    _add_joint(core, body, b, frozen, degree)
    return body


def _add_mesh(spec: mujoco.MjSpec, b: BodySpec) -> str:
    """The mesh asset of a ``mesh`` body: its vertices and triangles (none: MuJoCo makes the hull), its
    scale, and the hull's mass properties (MuJoCo collides a mesh as its convex hull; the Exudyn core
    takes the same hull for both)."""
    name = MESH_PREFIX + b.name
    mesh = spec.add_mesh(name=name, uservert=[float(x) for v in b.mesh.vertices for x in v],
                         scale=list(b.scale), inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_CONVEX)
    if b.mesh.faces:
        mesh.userface = [int(i) for f in b.mesh.faces for i in f]
    return name


def _geom_size(core: str, b: BodySpec) -> list[float]:
    s = [float(x) for x in b.size]
    need = {"plane": (0, 2), "box": (3,), "sphere": (1,), "capsule": (2,), "cylinder": (2,), "mesh": (0,)}[b.shape]
    if b.shape == "mesh":
        return [0.0, 0.0, 0.0]
    if len(s) not in need or any(x < 0 for x in s) or (b.shape != "plane" and not all(s)):
        raise fail(core, f"{_where(b)}a {b.shape} needs {' or '.join(map(str, need))} positive sizes, "
                   f"got {tuple(b.size)}")
    if b.shape == "plane":
        return [*(s or [0.0, 0.0]), 1.0]
    if b.shape == "box":
        return [x / 2 for x in s]
    if b.shape == "sphere":
        return [s[0], 0.0, 0.0]
    return [s[0], s[1] / 2, 0.0]


def _add_joint(core: str, body: mujoco.MjsBody, b: BodySpec, frozen: bool, degree: bool = False) -> None:
    kind = b.joint.kind if b.joint is not None else ("free" if b.parent is None else "fixed")
    if b.shape == "plane" and ((b.joint is not None and kind != "fixed") or b.parent is not None):
        raise fail(core, f"{_where(b)}a plane is static: it takes no joint and no parent")
    if b.shape == "plane" or kind == "fixed" or frozen:
        return
    name = (b.joint.name if b.joint is not None else None) or b.name
    if kind == "free":
        if b.parent is not None:
            raise fail(core, f"{_where(b)}a free joint needs a top-level body (mujoco)")
        body.add_freejoint(name=name)
        return
    if kind not in _JOINTS:
        raise fail(core, f"{_where(b)}joint kind {kind!r} is not supported by the mujoco core "
                   f"(supported: free, hinge, slide, fixed)" + did_you_mean(kind, _JOINTS))
    j = b.joint
    joint = body.add_joint(name=name, type=_JOINTS[kind], axis=list(j.axis), pos=list(j.anchor),
                           damping=float(j.damping))
    if j.range is not None:
        joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        scale = 180.0 / np.pi if degree and kind == "hinge" else 1.0  # a model file's spec may be in degrees
        joint.range = [float(j.range[0]) * scale, float(j.range[1]) * scale]


def _geom_owners(spec: mujoco.MjSpec) -> dict[str, str]:
    """Geom name -> the name of the body it belongs to (every geom is named by `_name_everything`)."""
    return {g.name: b.name for b in spec.bodies[1:] for g in b.geoms}


def _name_everything(spec: mujoco.MjSpec) -> None:
    """Give unnamed bodies, joints, actuators, sensors and geoms a name (structures map them by name)."""
    groups = (("body", spec.bodies[1:]), ("joint", spec.joints), ("actuator", spec.actuators),
              ("sensor", spec.sensors), ("geom", spec.geoms))
    for kind, items in groups:
        taken = {x.name for x in items}
        for i, item in enumerate(items):
            if not item.name:
                name = f"_{kind}{i}"
                while name in taken:
                    name += "_"
                item.name = name
                taken.add(name)


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
        kind = _GEOM_NAMES.get(int(model.geom_type[g]), "unknown")
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
    _size_arena(spec, source.size(edits))
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


def _bake(body: mujoco.MjsBody, rel: tuple | None, spec: mujoco.MjSpec) -> set[str]:
    """Give a body of an MJCF spec its frozen pose in its parent and remove its joints."""
    if rel is None:
        return set()
    if body.frame is not None:  # the baked pose is in the parent's frame: move the body to an identity frame
        body.set_frame(body.parent.add_frame())
    body.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
    body.pos, body.quat = list(rel[:3]), list(rel[3:])
    removed = set()
    for joint in list(body.joints):
        removed.add(joint.name)
        spec.delete(joint)
    return removed


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
