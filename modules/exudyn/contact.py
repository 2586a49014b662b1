"""Contacts of the Exudyn core: Exudyn's general contact (penalty spheres against spheres and triangles),
with parameters derived from the core's run-time parameters, and collision filters as contact sets.

Parameters. Every item of a body of mass m that rests on ``support`` of its spheres gets the
stiffness ``m wn^2 / support``; a sphere also gets the damping ``2 zeta wn m / support``. So a body
resting on its supports oscillates at ``wn`` rad/s with damping ratio ``zeta`` whatever its mass,
and sinks ``g / wn^2``. Exudyn puts the stiffnesses of a sphere and what it touches in series (the
softer one rules: a light body never meets the stiffness of a heavy one, which an explicit step could
not follow) and their dampings in parallel. So contacts come in two tiers: moving spheres against
static triangles (floors, static and frozen bodies' faces) with the damping above, and moving
bodies among themselves (and against static spheres) with a sphere's damping capped at
``DAMPING_CAP`` times the lightest moving mass over the step (a heavy body's damper must not shake
a light one apart; heavy bodies then bounce off each other a little more than the restitution
says). Static items are rigid (`RIGID`); static spheres damp at that cap. ``zeta`` comes from the
coefficient of restitution (`exudyn.calibrate`); the damper may pull until the contact separates
(``keepContactWhilePenetrating``). Friction is Coulomb's,
regularised below ``friction_zone`` m/s (a body with coefficients of its own gives its friction to its
contacts with bodies without; two bodies with their own take the larger). A body's own restitution sets
the damping of its spheres: it rules its contacts with static triangles (floors, frozen bodies) and
with moving triangles its spheres touch (two spheres: both dampers act, in parallel).
Triangle stiffness cannot change after a system is built: the core builds it again when the
contact frequency changes.

Filters. Exudyn's contact has no per-pair exclusion, only separate contact sets: a pair of items
interacts when both are in one set (a sphere hits the triangles and, when the set says so, the
spheres of the set). Without `no_collision` each tier is one set. With it, bodies of no group share a
set; each grouped body's spheres get a set with the triangles of the bodies it may touch (bodies
that exclude one another and see the same others, as the links of a kinematic tree, share one);
and sphere-on-sphere contact of a grouped body gets a set per allowed pair where one of the two has
no triangles to be hit (a ball, a cable); between two meshed bodies spheres against triangles do.
Spheres of one rigid body never touch its own triangles (Exudyn skips them).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

RIGID = 1.0e12
"""Stiffness (N/m) of static items: in series with a moving item's, it leaves that one's."""
DAMPING_CAP = 0.1
"""Largest damping of a sphere against other moving bodies, times the lightest moving mass over the
step: at a box's corner the mass a contact moves is down to a fifth of the body's (its rotation), and
velocity Verlet needs c h / m below about 2 (measured: a 60 g box dropped on a 5 kg box gains energy
with 0.2, not with 0.1)."""


@dataclass
class BodyItems:
    """The contact items of one body: sphere markers and radii, and a triangle mesh on a marker."""

    body: str
    mass: float
    """Mass of the carrier the body rides on (0 when static)."""
    support: int
    round: bool
    material: int
    spheres: list[tuple[int, float]] = field(default_factory=list)
    mesh: tuple[int, np.ndarray, np.ndarray] | None = None
    static: bool = False


@dataclass
class ContactSets:
    """The general contacts of a structure and the handles needed to change their parameters."""

    sets: list = field(default_factory=list)
    handles: list[tuple[object, int, float, int, bool, str]] = field(default_factory=list)
    """(general contact, sphere index in it, mass (-1: static), support, damping capped, body) of every sphere."""


def plan_sets(items: list[BodyItems], excluded: dict[str, set[str]],
              meshless: set[str] | None = None) -> list[tuple[list, list, bool]]:
    """(sphere bodies, triangle bodies, sphere-sphere contact) of each contact set (see the module docstring).
    Grouped bodies that exclude one another and see the same others share their set. ``meshless``: the
    bodies without triangles (default: those of ``items``)."""
    names = [it.body for it in items]
    if not any(excluded.get(n) for n in names):
        return [(names, names, True)]
    free = [n for n in names if not excluded.get(n)]
    sets = [(free, names, True)]
    classes: dict[frozenset, list[str]] = {}
    for x in names:
        if excluded.get(x):
            classes.setdefault(frozenset(excluded[x] | {x}), []).append(x)
    by_name = {it.body: it for it in items}
    if meshless is None:
        meshless = {it.body for it in items if it.mesh is None}
    for members in classes.values():
        x = members[0]
        shared = len(members) > 1 and all(m in excluded[x] for m in members[1:])
        for group in ([members] if shared else [[m] for m in members]):
            allowed = [n for n in names if n not in group and n not in excluded[group[0]]]
            sets.append((group, allowed, False))
            for g in group:
                for y in allowed:
                    both = by_name[g].spheres and by_name[y].spheres
                    if (y in free or y > g) and both and (g in meshless or y in meshless):
                        sets.append(([g, y], [], True))
    return sets


def build_sets(mbs, items: list[BodyItems], excluded: dict[str, set[str]], box: tuple[np.ndarray, np.ndarray],
               n_materials: int, wn: float) -> ContactSets:
    """Create the general contacts of ``items`` in ``mbs`` (parameters are set by `apply`), in two tiers:
    moving spheres against static triangles (the world: full damping), and moving bodies among
    themselves and against static spheres (damping capped, see the module docstring)."""
    out = ContactSets()
    moving = [it for it in items if not it.static]
    world = [replace(it, mesh=None) for it in moving] + [replace(it, spheres=[]) for it in items if it.static]
    bodies = moving + [replace(it, mesh=None) for it in items if it.static and it.spheres]
    meshless = {it.body for it in items if it.mesh is None}
    for tier, capped in ((world, False), (bodies, True)):
        by_name = {it.body: it for it in tier}
        for spheres, triangles, sphere_sphere in plan_sets(tier, excluded, meshless):
            mesh_items = [by_name[n] for n in triangles if by_name[n].mesh is not None]
            sphere_items = [by_name[n] for n in spheres if by_name[n].spheres]
            sphere_sphere = sphere_sphere and capped and _count(sphere_items) > 1
            moves = any(not it.static for it in sphere_items + mesh_items)  # static against static: no force
            if sphere_items and (mesh_items or sphere_sphere) and moves:
                out.sets.append(_contact(mbs, sphere_items, mesh_items, sphere_sphere, box, n_materials, wn,
                                         out.handles, capped))
    return out


def _contact(mbs, sphere_items: list[BodyItems], mesh_items: list[BodyItems], sphere_sphere: bool, box,
             n_materials: int, wn: float, handles: list, capped: bool):
    gc = mbs.AddGeneralContact()
    gc.verboseMode = 0
    gc.keepContactWhilePenetrating = True
    gc.sphereSphereContact = sphere_sphere
    gc.resetSearchTreeInterval = 2**30  # never re-create the cells: their order is no state we restore
    gc.SetFrictionPairings(np.ones((n_materials, n_materials)))
    for it in sorted(mesh_items, key=lambda it: not it.static):  # static triangles come first
        marker, points, tris = it.mesh
        stiffness = RIGID if it.static else it.mass / max(it.support, 1) * wn * wn
        gc.AddTrianglesRigidBodyBased(rigidBodyMarkerIndex=marker, contactStiffness=stiffness, contactDamping=0.0,
                                      frictionMaterialIndex=it.material, pointList=points.tolist(),
                                      triangleList=tris.tolist(), staticTriangles=it.static)
    for it in sphere_items:
        for marker, radius in it.spheres:
            index = gc.AddSphereWithMarker(marker, radius=float(radius), contactStiffness=RIGID if it.static else 1.0,
                                           contactDamping=0.0, frictionMaterialIndex=it.material)
            handles.append((gc, index, -1.0 if it.static else it.mass, it.support, capped, it.body))
    _search_tree(gc, box, _count(sphere_items) + sum(len(it.mesh[2]) for it in mesh_items))
    return gc


def _count(items: list[BodyItems]) -> int:
    return sum(len(it.spheres) for it in items)


def _search_tree(gc, box: tuple[np.ndarray, np.ndarray], n_items: int) -> None:
    low, high = box
    extent = np.maximum(high - low, 1e-3)
    cells = max(1.0, min(4096.0, n_items / 2.0))
    scale = (cells / float(np.prod(extent))) ** (1.0 / 3.0)
    gc.SetSearchTreeCellSize([int(min(32, max(1, round(e * scale)))) for e in extent])
    gc.SetSearchTreeBox(low.tolist(), high.tolist())


def apply(contacts: ContactSets, *, wn: float, zeta: float, friction_zone: float, pairings: np.ndarray,
          step: float, lightest: float, zetas: dict[str, float] | None = None) -> None:
    """Set stiffness, damping and friction of every contact sphere from the core's parameters;
    ``zetas``: the damping ratio of the bodies with a restitution of their own (`exudyn.calibrate`)."""
    zetas = zetas or {}
    for gc in contacts.sets:
        gc.SetFrictionPairings(pairings)
        gc.frictionProportionalZone = float(friction_zone)
    cap = DAMPING_CAP * lightest / step
    for gc, index, mass, support, capped, body in contacts.handles:
        if mass < 0:  # a static sphere: rigid, damped at the cap (the moving triangles it meets have none)
            gc.SetSphereMarkerBased(index, contactDamping=cap)
            continue
        share = mass / max(support, 1)
        damping = 2.0 * zetas.get(body, zeta) * wn * share
        gc.SetSphereMarkerBased(index, contactStiffness=share * wn * wn,
                                contactDamping=min(damping, cap) if capped else damping)


def pairings(base: float, materials: list[float | None]) -> np.ndarray:
    """Friction coefficient of each pair of materials (material 0: the bodies with no coefficients of their
    own, ``base``; the others a body's own friction, None: ``base``): a body's own material rules its
    contacts with the others; between two bodies with their own, the larger."""
    mu = np.array([base if m is None else m for m in materials], dtype=float)
    out = np.maximum.outer(mu, mu)
    out[0, :], out[:, 0] = mu, mu
    return out

