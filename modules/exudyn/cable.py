"""Cables of the Exudyn core: a rope of 3D ANCF cable elements (``ObjectANCFCable``: position and slope at
each node; axial and bending stiffness, no torsion), touching other bodies through a sphere of its
radius at every node but a pinned end (which sits inside what holds it), its ends pinned by springs.
A cable resists compression as it resists stretching: a slack rope stays straight until it buckles
(quickly when it is long, thin and has many segments).

Pins. A pin is a Cartesian spring between the cable's end node and a point of the world or of a body
(where the end was at t=0). Its stiffness is one element's axial stiffness EA/l, so it stretches like
one more element and needs no smaller step than the cable itself; its damping ratio is
``PIN_ZETA``. (A position constraint would be exact, but an explicit solver does not keep one.)

Step. Velocity Verlet was measured stable up to ``AXIAL_LIMIT`` times the time an axial wave takes to
cross an element, ``l / sqrt(EA / (rho A))``, and up to ``BENDING_LIMIT`` times the bending analogue
``l^2 / sqrt(EI / (rho A))``: so the highest frequencies are about ``2 / (limit * time)``. Damping
proportional to stiffness damps a mode of frequency w with ratio ``damping * w / 2``, which lowers
the stable step to ``2 / w * (sqrt(1 + zeta^2) - zeta)``. `stable_step` is ``SAFETY`` times the
smallest of these, and the core never steps a cable with a larger step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from exudyn.itemInterface import (
    LoadMassProportional,
    MarkerBodyMass,
    MarkerBodyPosition,
    MarkerNodePosition,
    NodePointSlope1,
    ObjectANCFCable,
    ObjectConnectorCartesianSpringDamper,
)

from dynabrain.orchestrator.kernel.core import BodySpec

from . import contact as xk
from . import geometry as geo

if TYPE_CHECKING:
    from .plan import Carrier
    from .system import Start, System

PIN_ZETA = 0.3
AXIAL_LIMIT = 0.133
BENDING_LIMIT = 0.032
SAFETY = 0.5


@dataclass
class CableParts:
    name: str
    frozen: bool
    segments: int
    nodes: list[int] = field(default_factory=list)
    loads: list[int] = field(default_factory=list)
    coords: np.ndarray | None = None
    """Node coordinates (n+1, 6) of a frozen cable."""
    ref: np.ndarray | None = None
    """Reference coordinates (n+1, 6) of the nodes of a moving cable (Exudyn's coordinates are from it)."""


def mass(b: BodySpec) -> float:
    length = float(np.linalg.norm(np.subtract(b.cable.end, b.pos)))
    return float(b.mass) if b.mass is not None else geo.DENSITY * math.pi * b.size[0] ** 2 * length


def reference(b: BodySpec) -> np.ndarray:
    """Node coordinates (n+1, 6) of the straight cable at t=0: positions and unit slopes."""
    start, end = np.asarray(b.pos, dtype=float), np.asarray(b.cable.end, dtype=float)
    n = b.cable.segments
    direction = (end - start) / np.linalg.norm(end - start)
    points = start + np.outer(np.linspace(0.0, 1.0, n + 1), end - start)
    return np.hstack([points, np.tile(direction, (n + 1, 1))])


def stable_step(b: BodySpec) -> float:
    """The largest explicit step (s) the cable takes (see the module docstring)."""
    c = b.cable
    length = float(np.linalg.norm(np.subtract(c.end, b.pos)))
    element = length / c.segments
    rho_a = mass(b) / length
    steps = []
    for limit, time in ((AXIAL_LIMIT, element / math.sqrt(c.axial_stiffness / rho_a)),
                        (BENDING_LIMIT, element * element / math.sqrt(c.bending_stiffness / rho_a))):
        w = 2.0 / (limit * time)
        zeta = c.damping * w / 2.0
        steps.append(2.0 / w * (math.sqrt(1.0 + zeta * zeta) - zeta))
    return SAFETY * min(steps)


def tip_pose(coords: np.ndarray) -> geo.Pose:
    """Pose of a cable's end: its position, x along the slope there."""
    return geo.pose(coords[-1, :3], geo.direction_quat(coords[-1, 3:]))


def build(system: System, carrier: Carrier, start: Start) -> CableParts:
    name = carrier.owner
    b = system.top.spec[name]
    ref = reference(b)
    n = b.cable.segments
    material = system.material(b.friction)
    if carrier.kind == "frozen_cable":
        coords = system.plan.frozen_cables[name].reshape(n + 1, 6)
        parts = CableParts(name, True, n, coords=coords)
        if name in system.plan.absent:  # out of the simulation: no contact spheres
            return parts
        item = xk.BodyItems(name, 0.0, n + 1, True, material, static=True)
        pinned = {i for i, target in zip((0, n), b.cable.attach, strict=True) if target is not None}
        for p in (p for i, p in enumerate(coords[:, :3]) if i not in pinned):
            item.spheres.append((system.mbs.AddMarker(MarkerBodyPosition(bodyNumber=system.ground,
                                                                            localPosition=list(map(float, p)))),
                                 float(b.size[0])))
        system.items.append(item)
        return parts
    coords, vel = start.cables.get(name, (ref.reshape(-1), np.zeros(ref.size)))
    coords, vel = np.asarray(coords).reshape(n + 1, 6), np.asarray(vel).reshape(n + 1, 6)
    c = b.cable
    length = float(np.linalg.norm(np.subtract(c.end, b.pos)))
    total = mass(b)
    parts = CableParts(name, False, n, ref=ref)
    mbs = system.mbs
    for i in range(n + 1):
        parts.nodes.append(mbs.AddNode(NodePointSlope1(referenceCoordinates=ref[i].tolist(),
                                                          initialCoordinates=(coords[i] - ref[i]).tolist(),
                                                          initialVelocities=vel[i].tolist())))
    for i in range(n):
        element = mbs.AddObject(ObjectANCFCable(
            nodeNumbers=[parts.nodes[i], parts.nodes[i + 1]], length=length / n, massPerLength=total / length,
            bendingStiffness=c.bending_stiffness, axialStiffness=c.axial_stiffness,
            bendingDamping=c.bending_stiffness * c.damping, axialDamping=c.axial_stiffness * c.damping))
        marker = mbs.AddMarker(MarkerBodyMass(bodyNumber=element))
        parts.loads.append(mbs.AddLoad(LoadMassProportional(markerNumber=marker, loadVector=[0.0, 0.0, 0.0])))
    item = xk.BodyItems(name, total, n + 1, True, material)
    pinned = {i for i, target in zip((0, n), c.attach, strict=True) if target is not None}
    for i, node in enumerate(parts.nodes):
        if i not in pinned:  # a pinned end sits inside what holds it: no sphere there
            item.spheres.append((mbs.AddMarker(MarkerNodePosition(nodeNumber=node)), float(b.size[0])))
    system.items.append(item)
    return parts


def pin(system: System, parts: CableParts) -> None:
    """Pin the cable's ends to what ``attach`` names (call once every carrier exists)."""
    b = system.top.spec[parts.name]
    c = b.cable
    ref = reference(b)
    length = float(np.linalg.norm(np.subtract(c.end, b.pos)))
    element = length / c.segments
    k = c.axial_stiffness / element
    node_mass = mass(b) / c.segments
    d = 2.0 * PIN_ZETA * math.sqrt(k * node_mass)
    mbs = system.mbs
    for end, target in zip((0, c.segments), c.attach, strict=True):
        if target is None:
            continue
        point = ref[end, :3]
        holder = system.point_marker(target, point)
        if parts.frozen:
            if holder is None:
                continue
            held = mbs.AddMarker(MarkerBodyPosition(bodyNumber=system.ground,
                                                       localPosition=list(map(float, parts.coords[end, :3]))))
        else:
            held = mbs.AddMarker(MarkerNodePosition(nodeNumber=parts.nodes[end]))
            if holder is None:  # a static holder: a fixed point of the world
                holder = system.world_marker(target, point)
        mbs.AddObject(ObjectConnectorCartesianSpringDamper(markerNumbers=[holder, held], stiffness=[k] * 3,
                                                             damping=[d] * 3))
