"""Where a MuJoCo core's model comes from (`SpecSource`): a SceneSpec of primitives or an MJCF file made
into a fresh `mujoco.MjSpec` for each structure (`mujoco.scene` compiles them), the names the core gives
what it adds, and the size of MuJoCo's memory for a step (`ModelSize`, `arena_bytes`).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from typing import NamedTuple

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.core import FLEX_SHAPES, SHAPES, BodySpec, Edits, SceneSpec, scene_bodies
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.suggest import did_you_mean

from . import options, refs

ENGINE = "mujoco"
_GEOMS = {"plane": mujoco.mjtGeom.mjGEOM_PLANE, "box": mujoco.mjtGeom.mjGEOM_BOX,
          "sphere": mujoco.mjtGeom.mjGEOM_SPHERE, "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
          "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER, "mesh": mujoco.mjtGeom.mjGEOM_MESH}
GEOM_NAMES = {int(v): k for k, v in _GEOMS.items()} | {
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


def size_arena(spec: mujoco.MjSpec, size: ModelSize) -> None:
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
