"""What the Exudyn core makes of a scene: the topology of its bodies, and for each structure (frozen
objects, welds) the *carriers* that move them.

A carrier is one thing Exudyn integrates; every body rides on exactly one, at a fixed pose in the
carrier's owner body frame:

- ``world``: static bodies (planes, fixed top-level bodies and what hangs on them without a joint,
  frozen objects), at their world poses;
- ``free``: a rigid body node (a free top-level body, with its fixed descendants merged in);
- ``link``: a link of a kinematic tree (a body on a hinge or slide joint, with its fixed
  descendants); a tree hangs from the world or from a static body, in minimal coordinates;
- ``cable``: a flexible rope (`CableSpec`), or ``frozen_cable`` when it is not simulated.

`make_joint` welds by merging carriers: two free carriers become one rigid body, a free carrier
welded to a link rides on the link, one welded to the world becomes static. So a weld is exact
(no spring), and `remove_joint` splits them again. Two jointed bodies cannot be welded (it would
close a kinematic loop), and a cable cannot be welded: both are refused with the reason.

The body order (the rows of the block ports) is MuJoCo's: depth first, parents made before
children, so both cores give the same port layout for the same scene.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from dynabrain.orchestrator.kernel.core import FLEX_SHAPES, SHAPES, BodySpec, SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.suggest import did_you_mean

from . import geometry as geo

ENGINE = "exudyn"
_SIZE_LEN = {"plane": (0, 2), "box": (3,), "sphere": (1,), "capsule": (2,), "cylinder": (2,), "cable": (1,),
             "mesh": (0,)}


def fail(core: str, message: str) -> DynabrainError:
    return DynabrainError(f"{ENGINE} core {core!r}: {message}")


def where(b: BodySpec) -> str:
    return f"body {b.name!r}" + (f" (line {b.line})" if b.line else "") + ": "


@dataclass(frozen=True)
class Topology:
    """The scene as the core sees it; fixed for the core's life (structures only regroup it)."""

    core: str
    spec: dict[str, BodySpec]
    bodies: tuple[str, ...]
    parents: tuple[str | None, ...]
    objects: tuple[str, ...]
    subtree: dict[str, tuple[str, ...]]
    role: dict[str, str]
    """plane, static, free, fixed, link or cable."""
    joint_of: dict[str, str]
    """Body -> its joint's name (free, hinge and slide joints)."""
    joints: tuple[str, ...]
    qjoints: tuple[str, ...]
    joint_body: dict[str, str]
    world: dict[str, geo.Pose]
    """World pose of every body at t=0 (joints at 0); a cable's is its start, x along it."""
    owner: dict[str, str]
    """The body whose carrier a body rides on at t=0 ('' for the world)."""
    rel: dict[str, geo.Pose]
    """Pose of a body in its owner's frame (the world frame for the world)."""
    tree_of: dict[str, str] = field(default_factory=dict)
    """Link body -> the root link of its kinematic tree."""

    @property
    def free(self) -> frozenset[str]:
        return frozenset(b for b, r in self.role.items() if r == "free")

    def free_bodies(self) -> tuple[str, ...]:
        """The free bodies in body order: the rows of the ``body_wrench`` and ``body_velocity`` inputs."""
        return tuple(b for b in self.bodies if self.role[b] == "free")

    def qunit(self, joint: str) -> tuple[str, str]:
        kind = self.spec[self.joint_body[joint]].joint.kind
        return ("rad", "N*m") if kind == "hinge" else ("m", "N")


def analyse(core: str, scene: SceneSpec) -> Topology:
    """The topology of a scene of primitives; refuses what the exudyn core cannot simulate."""
    if scene.model:
        raise fail(core, f"a model file ({scene.model}) is not supported by the exudyn core: it simulates scenes "
                   "of primitives (plane, box, sphere, capsule, cylinder, cable); use core: mujoco for MJCF or URDF")
    spec = _check_names(core, scene.bodies)
    for b in scene.bodies:
        _check_body(core, b, spec)
    order = _order(core, scene.bodies, spec)
    parents = tuple(spec[n].parent for n in order)
    subtree = {n: [n] for n in order}
    for n in reversed(order):
        if spec[n].parent is not None:
            subtree[spec[n].parent].extend(subtree[n])
    role = _roles(core, order, spec)
    joint_of = {n: (spec[n].joint.name if spec[n].joint else None) or n for n in order if role[n] in ("free", "link")}
    world, owner, rel = _poses(order, spec, role)
    tree_of = {}
    for n in order:
        if role[n] == "link":
            p = spec[n].parent
            tree_of[n] = tree_of[p] if p is not None and role[p] == "link" else n
    joints = tuple(joint_of[n] for n in order if n in joint_of)
    if len(set(joints)) != len(joints):
        dup = sorted({j for j in joints if joints.count(j) > 1})
        raise fail(core, f"joint names must be unique; repeated: {', '.join(dup)}")
    taken = set(order) - set(joint_of)
    clash = [j for n, j in joint_of.items() if j != n and j in taken]
    if clash:
        raise fail(core, f"joint name(s) {', '.join(clash)} are also body names")
    return Topology(core=core, spec=spec, bodies=order, parents=parents,
                    objects=tuple(n for n in order if spec[n].parent is None),
                    subtree={k: tuple(v) for k, v in subtree.items()}, role=role, joint_of=joint_of, joints=joints,
                    qjoints=tuple(joint_of[n] for n in order if role[n] == "link"),
                    joint_body={j: n for n, j in joint_of.items()}, world=world, owner=owner, rel=rel,
                    tree_of=tree_of)


def _check_names(core: str, bodies: Sequence[BodySpec]) -> dict[str, BodySpec]:
    names = [b.name for b in bodies]
    spec = {b.name: b for b in bodies}
    if len(spec) != len(bodies):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise fail(core, f"body names must be unique; repeated: {', '.join(dup)}")
    return spec


def _check_body(core: str, b: BodySpec, spec: dict[str, BodySpec]) -> None:
    if b.shape not in SHAPES and b.shape not in FLEX_SHAPES:
        known = (*SHAPES, *FLEX_SHAPES)
        raise fail(core, f"{where(b)}shape {b.shape!r} is not supported by the exudyn core (supported: "
                   f"{', '.join(known)})" + did_you_mean(b.shape, known))
    s = tuple(float(x) for x in b.size)
    need = _SIZE_LEN[b.shape]
    if b.shape == "mesh" and b.mesh is None:
        raise fail(core, f"{where(b)}a mesh body needs its mesh")
    if len(s) not in need or any(x <= 0 for x in s):
        raise fail(core, f"{where(b)}a {b.shape} needs {' or '.join(map(str, need))} positive sizes, got {b.size}")
    if b.mass is not None and not b.mass > 0:
        raise fail(core, f"{where(b)}mass must be positive, got {b.mass}")
    if b.parent is not None and b.parent not in spec:
        raise fail(core, f"{where(b)}parent {b.parent!r} is not a body" + did_you_mean(b.parent, spec))
    kind = b.joint.kind if b.joint is not None else None
    if kind not in (None, "free", "fixed", "hinge", "slide"):
        raise fail(core, f"{where(b)}joint kind {kind!r} is not supported by the exudyn core "
                   "(supported: free, hinge, slide, fixed)")
    if b.shape == "plane" and (kind not in (None, "fixed") or b.parent is not None):
        raise fail(core, f"{where(b)}a plane is static: it takes no joint and no parent")
    if b.shape in FLEX_SHAPES:
        _check_cable(core, b, spec)
    elif b.cable is not None:
        raise fail(core, f"{where(b)}only a cable has cable fields")
    if kind in ("hinge", "slide") and not np.linalg.norm(b.joint.axis) > 0:
        raise fail(core, f"{where(b)}a joint axis cannot be zero")


def _check_cable(core: str, b: BodySpec, spec: dict[str, BodySpec]) -> None:
    c = b.cable
    if c is None or b.parent is not None or b.joint is not None:
        raise fail(core, f"{where(b)}a cable is top-level, has no joint and needs its cable fields (end, ...)")
    if np.allclose(b.pos, c.end):
        raise fail(core, f"{where(b)}a cable's ends must differ")
    if not (c.segments >= 1 and c.axial_stiffness > 0 and c.bending_stiffness > 0 and c.damping >= 0):
        raise fail(core, f"{where(b)}a cable needs segments >= 1, positive stiffnesses and damping >= 0")
    for end in c.attach:
        if end not in (None, "world") and (end not in spec or end == b.name or spec[end].shape in FLEX_SHAPES):
            raise fail(core, f"{where(b)}a cable end is attached to {end!r}, which is not a rigid body"
                       + did_you_mean(str(end), spec))


def _order(core: str, bodies: Sequence[BodySpec], spec: dict[str, BodySpec]) -> tuple[str, ...]:
    """Depth-first, children in the order they were made, parents made first (MuJoCo's body order)."""
    children: dict[str | None, list[str]] = {None: []}
    made: set[str] = set()

    def make(name: str, chain: tuple[str, ...]) -> None:
        if name in made:
            return
        parent = spec[name].parent
        if parent in chain:
            raise fail(core, f"{where(spec[name])}parent cycle: {' -> '.join((*chain, name))}")
        if parent is not None:
            make(parent, (*chain, name))
        made.add(name)
        children.setdefault(parent, []).append(name)
        children.setdefault(name, [])

    for b in bodies:
        make(b.name, ())
    out: list[str] = []
    stack = list(reversed(children[None]))
    while stack:
        name = stack.pop()
        out.append(name)
        stack.extend(reversed(children[name]))
    return tuple(out)


def _roles(core: str, order: tuple[str, ...], spec: dict[str, BodySpec]) -> dict[str, str]:
    role: dict[str, str] = {}
    carrier: dict[str, str] = {}  # role of the carrier a body rides on
    for n in order:
        b = spec[n]
        kind = b.joint.kind if b.joint is not None else None
        if b.shape == "plane":
            role[n] = "plane"
        elif b.shape in FLEX_SHAPES:
            role[n] = "cable"
        elif b.parent is None:
            role[n] = {None: "free", "free": "free", "fixed": "static"}.get(kind, "link")
        elif kind == "free":
            raise fail(core, f"{where(b)}a free joint needs a top-level body (exudyn)")
        elif kind in ("hinge", "slide"):
            if carrier[b.parent] == "free":
                raise fail(core, f"{where(b)}a {kind} joint under a free body (a floating chain) is not supported "
                           "by the exudyn core; hang the chain from the world or a fixed body")
            role[n] = "link"
        else:
            role[n] = "fixed"
        carrier[n] = carrier[b.parent] if role[n] == "fixed" else role[n]
    return role


def _poses(order: tuple[str, ...], spec: dict[str, BodySpec], role: dict[str, str]):
    world: dict[str, geo.Pose] = {}
    owner: dict[str, str] = {}
    rel: dict[str, geo.Pose] = {}
    for n in order:
        b = spec[n]
        if role[n] == "cable":
            world[n] = geo.pose(b.pos, geo.direction_quat(np.subtract(b.cable.end, b.pos)))
        else:
            local = geo.pose(b.pos, b.quat)
            world[n] = local if b.parent is None else geo.compose(world[b.parent], local)
        if role[n] == "fixed":
            owner[n] = owner[b.parent]
            parent_rel = rel[b.parent] if owner[n] else world[b.parent]
            rel[n] = geo.compose(parent_rel, geo.pose(b.pos, b.quat)) if owner[n] else world[n]
        elif role[n] in ("plane", "static"):
            owner[n], rel[n] = "", world[n]
        else:
            owner[n], rel[n] = n, geo.IDENTITY
    return world, owner, rel
