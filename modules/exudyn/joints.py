"""Joints made at run time in the Exudyn core: hinges, sliders and balls (`make_joint` with a ``kind``;
a weld merges carriers instead, exactly: `exudyn.plan`).

Exudyn's explicit solvers integrate no algebraic constraint between bodies, so these joints are
stiff springs: one ``ObjectConnectorRigidBodySpringDamper`` between the joint's frame on each body's
carrier (`kernel.bodies.JointFrames`: origin at the anchor, z along the axis), stiff in the directions
the joint holds and free in the others: a hinge leaves the turn about z free, a slider the motion
along z, a ball every turn. Each direction is as stiff as the contacts (natural frequency ``wn`` of
the mass, or inertia, the joint moves: the two carriers' in series, as seen at the anchor) and
critically damped, so an explicit step stays stable and the joint gives way by ``load / (m wn^2)``
(about 10 um under gravity at the default 0.5 ms engine step). Between a free body, a link of a
kinematic tree and the world (or a static body) alike, and no kinematic loop to refuse.
"""

from __future__ import annotations

from dataclasses import dataclass

import exudyn as exu
import numpy as np
from exudyn.itemInterface import (
    MarkerBodyRigid,
    MarkerKinematicTreeRigid,
    ObjectConnectorRigidBodySpringDamper,
)

from . import geometry as geo
from .topology import fail

HELD = {"hinge": (1, 1, 1, 1, 1, 0), "slider": (1, 1, 0, 1, 1, 1), "ball": (1, 1, 1, 0, 0, 0)}
"""The directions each kind holds, in its frame: x, y, z translations, then turns about x, y, z."""
ZETA = 1.0
"""Damping ratio of a joint's springs (critical)."""


@dataclass
class Spring:
    """One joint made at run time, as Exudyn holds it: the connector and what its stiffness follows."""

    connector: int
    mass: float
    """The mass the joint moves along a held direction (the two carriers in series at the anchor)."""
    inertia: float
    """The inertia it turns about a held direction."""
    held: np.ndarray


def build(system, welds) -> list[Spring]:
    """A connector for each hinge, slider and ball of ``welds`` (`Weld`s) in ``system`` (a
    `exudyn.system.System` whose carriers are built); their stiffness is set by `apply`."""
    out = []
    for w in welds:
        sides = [_side(system, w, body, pos, quat) for body, pos, quat in ((w.a, w.data.pos_a, w.data.quat_a),
                                                                           (w.b, w.data.pos_b, w.data.quat_b))]
        if all(s[1] == np.inf for s in sides):
            continue  # both sides static (frozen, or welded to the world): nothing moves
        mass = 1.0 / sum(1.0 / s[1] for s in sides)
        inertia = 1.0 / sum(1.0 / s[2] for s in sides)
        zero = np.zeros((6, 6)).tolist()
        connector = system.mbs.AddObject(ObjectConnectorRigidBodySpringDamper(
            markerNumbers=[sides[0][0], sides[1][0]], stiffness=zero, damping=zero, useIntrinsicFormulation=False))
        out.append(Spring(connector, mass, inertia, np.array(HELD[w.kind], dtype=float)))
    return out


def apply(system, springs: list[Spring], wn: float) -> None:
    """Stiffness and damping of every joint for the contacts' natural frequency ``wn``."""
    for s in springs:
        scale = np.array([s.mass] * 3 + [s.inertia] * 3) * s.held
        system.mbs.SetObjectParameter(s.connector, "stiffness", np.diag(scale * wn * wn).tolist())
        system.mbs.SetObjectParameter(s.connector, "damping", np.diag(scale * 2.0 * ZETA * wn).tolist())


def _side(system, w, body: str, pos, quat) -> tuple[int, float, float]:
    """(marker at the joint frame on ``body``'s carrier, the mass and inertia the joint moves there;
    infinite for the world)."""
    frame = system.frames[body]
    x = geo.compose(frame.pose, geo.pose(pos, quat))  # the joint frame in the carrier's frame
    local = exu.HT(rotation=geo.quat_to_mat(x[1]).tolist(), translation=[float(v) for v in x[0]])
    mbs = system.mbs
    if frame.kind == "world":
        return mbs.AddMarker(MarkerBodyRigid(bodyNumber=system.ground, localHT=local)), np.inf, np.inf
    if frame.kind == "free":
        _node, rigid, _load = system.free[frame.index]
        mass, inertia = system.free_mass[frame.index], system.free_inertia[frame.index]
        arm = np.asarray(x[0])  # the carrier's node is at its centre of mass
        marker = mbs.AddMarker(MarkerBodyRigid(bodyNumber=rigid, localHT=local))
    elif frame.kind == "link":
        kt, link = system.link_ref[frame.index]
        spec = next(t["spec"] for t in system.trees if t["kt"] == kt)
        mass, inertia = spec.masses[link], np.asarray(spec.inertias[link])
        arm = np.asarray(x[0]) - spec.coms[link]
        marker = mbs.AddMarker(MarkerKinematicTreeRigid(objectNumber=kt, linkNumber=link, localHT=local))
    else:
        raise fail(system.top.core, f"make_joint({w.a!r}, {w.b!r}): {body!r} is a cable; the exudyn core pins "
                   "cables with attach, it makes no joint on them")
    return marker, *_effective(mass, inertia, arm)


def _effective(mass: float, inertia: np.ndarray, arm: np.ndarray) -> tuple[float, float]:
    """The smallest mass a force at ``arm`` from the centre of mass of a body of ``mass`` and ``inertia``
    (3x3, about its centre of mass) moves, over every direction, and the smallest principal inertia."""
    inertia = np.asarray(inertia, dtype=float) + 1e-12 * np.eye(3)
    skew = np.array([[0.0, -arm[2], arm[1]], [arm[2], 0.0, -arm[0]], [-arm[1], arm[0], 0.0]])
    turn = float(np.linalg.eigvalsh(skew.T @ np.linalg.solve(inertia, skew))[-1])
    return 1.0 / (1.0 / mass + turn), float(np.linalg.eigvalsh(inertia)[0])
