"""A structure of the Exudyn core, planned: which carrier every body rides on once the edits
(frozen objects, welds) are applied. See `exudyn.topology` for what a carrier is.

The edits are the kernel's `Edits` (immutable named tuples, so they compare, hash and pickle: they
are part of the core's state):

- ``frozen``: one `FrozenObject` per frozen object: where everything stood when it froze;
- ``absent``: the frozen objects out of the simulation (`make` with ``others="absent"``): their bodies stay
  on the world carrier, where they stood, for their outputs, but get no contact geometry (`Plan.absent`);
- ``welds``: one `Weld` per `make_joint`, a weld's ``data`` the pose of b in a's frame (7 values); the
  other kinds (hinge, slider, ball) are springs between carriers (`exudyn.joints`);
- ``groups``: sorted tuples of bodies that do not collide with one another (`no_collision`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from dynabrain.orchestrator.kernel.core import Edits
from dynabrain.orchestrator.kernel.portable import state_type

from . import geometry as geo
from .topology import Topology, fail


@state_type
class FrozenObject(NamedTuple):
    """The Exudyn core's entry of one frozen object in `Edits.frozen` (`ExudynCore._freeze_entry`)."""

    object: str
    bodies: tuple[tuple[str, tuple[float, ...]], ...]
    """(body, its world pose: x, y, z, qw, qx, qy, qz) for every body of the object's subtree."""
    joints: tuple[tuple[str, float], ...]
    """(joint, its value) for every hinge or slide joint of the subtree."""
    cables: tuple[tuple[str, tuple[float, ...]], ...]
    """(cable, its node coordinates, flat) for every cable of the subtree."""


@dataclass
class Carrier:
    owner: str
    kind: str
    """world, free, link, cable or frozen_cable."""
    members: dict[str, geo.Pose] = field(default_factory=dict)
    """Body -> its pose in the owner's frame (the world frame for the world)."""


@dataclass
class Plan:
    carriers: dict[str, Carrier]
    carrier_of: dict[str, str]
    trees: dict[str, list[str]]
    """Root link -> the links of an active kinematic tree, parents first."""
    frozen_joints: dict[str, float]
    frozen_cables: dict[str, np.ndarray]
    groups: tuple[tuple[str, ...], ...]
    joints: tuple = ()
    """The hinges, sliders and balls made at run time (`Weld`s): springs between carriers (`exudyn.joints`)."""
    absent: frozenset[str] = frozenset()
    """The bodies of absent objects (`Edits.absent`): on the world carrier for their outputs (where they
    stood), without contact geometry."""

    @property
    def world(self) -> Carrier:
        return self.carriers[""]


def to7(p: geo.Pose) -> tuple[float, ...]:
    return (*map(float, p[0]), *map(float, p[1]))


def from7(v) -> geo.Pose:
    return geo.pose(v[:3], v[3:])


def make_plan(top: Topology, edits: Edits) -> Plan:
    """The carriers of the structure ``edits``; refuses welds the core cannot make."""
    carriers: dict[str, Carrier] = {"": Carrier("", "world")}
    carrier_of: dict[str, str] = {}
    for n in top.bodies:
        own = top.owner[n]
        if own not in carriers:
            carriers[own] = Carrier(own, top.role[own])
        carriers[own].members[n] = top.rel[n]
        carrier_of[n] = own
    frozen_joints: dict[str, float] = {}
    frozen_cables: dict[str, np.ndarray] = {}
    for entry in edits.frozen:
        for body, world in entry.bodies:
            if top.role[body] != "cable":
                _move(carriers, carrier_of, body, "", from7(world))
        frozen_joints.update(entry.joints)
        for cable, coords in entry.cables:
            carriers[cable].kind = "frozen_cable"
            frozen_cables[cable] = np.asarray(coords, dtype=float)
    for weld in edits.welds:
        if weld.kind == "weld":
            _weld(top, carriers, carrier_of, weld.name, weld.a, weld.b, weld.data)
    carriers = {k: c for k, c in carriers.items() if c.members or k == ""}
    trees: dict[str, list[str]] = {}
    for n in top.bodies:
        if carriers.get(n) is not None and carriers[n].kind == "link":
            trees.setdefault(top.tree_of[n], []).append(n)
    absent = frozenset(b for entry in edits.frozen if entry.object in edits.absent for b, _x in entry.bodies)
    return Plan(carriers, carrier_of, trees, frozen_joints, frozen_cables, tuple(edits.groups),
                tuple(w for w in edits.welds if w.kind != "weld"), absent)


def _move(carriers: dict[str, Carrier], carrier_of: dict[str, str], body: str, dest: str, rel: geo.Pose) -> None:
    del carriers[carrier_of[body]].members[body]
    carriers[dest].members[body] = rel
    carrier_of[body] = dest


def _weld(top: Topology, carriers: dict[str, Carrier], carrier_of: dict[str, str], name: str, a: str, b: str,
          rel7) -> None:
    ca, cb = carriers[carrier_of[a]], carriers[carrier_of[b]]
    if ca is cb or (ca.kind == "world" and cb.kind == "world"):
        return
    for c, body in ((ca, a), (cb, b)):
        if c.kind in ("cable", "frozen_cable"):
            raise fail(top.core, f"make_joint({a!r}, {b!r}): {body!r} is a cable; the exudyn core pins cables "
                       "with attach, it does not weld them")
    x_ab = from7(rel7)
    if cb.kind == "free":
        _merge(carriers, carrier_of, into=ca, via=a, other=cb, other_body=b, x_via_other=x_ab)
    elif ca.kind == "free":
        _merge(carriers, carrier_of, into=cb, via=b, other=ca, other_body=a, x_via_other=geo.inverse(x_ab))
    else:
        what = "to the world" if "world" in (ca.kind, cb.kind) else "to another jointed body"
        raise fail(top.core, f"make_joint({a!r}, {b!r}) ({name}): welding a body on a hinge or slide joint {what} "
                   "would close a kinematic loop, which the exudyn core does not simulate")


def _merge(carriers: dict[str, Carrier], carrier_of: dict[str, str], *, into: Carrier, via: str, other: Carrier,
           other_body: str, x_via_other: geo.Pose) -> None:
    """Move every member of ``other`` onto ``into``, keeping ``other_body`` at ``x_via_other`` in ``via``."""
    x_into_via = into.members[via]
    x_other_inv = geo.inverse(other.members[other_body])
    base = geo.compose(geo.compose(x_into_via, x_via_other), x_other_inv)
    for m, x in list(other.members.items()):
        into.members[m] = geo.compose(base, x)
        carrier_of[m] = into.owner
    other.members.clear()
