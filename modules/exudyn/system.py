"""One structure of the Exudyn core built in Exudyn: the system, its explicit solver stepped from
Python, its state, and (with `exudyn.outputs`) the maps from bodies, joints and cables to Exudyn's
coordinates.

What each carrier becomes (see `exudyn.topology`):

- a free carrier: a rigid body on a Lie-group rotation-vector node (``NodeRigidBodyRotVecLG``) at its
  centre of mass, gravity as a mass-proportional load;
- the links of a tree: one ``ObjectKinematicTree`` (minimal coordinates, so joints are exact with an
  explicit solver), joint damping as its D control, joint ranges as limit stops
  (``CoordinateSpringDamperExt``), gravity its own;
- the world: static triangles and spheres on the ground;
- a cable: ANCF cable elements (`exudyn.cable`).

Solver: explicit, fixed step, one ``SolveSteps`` call per module step; velocity Verlet by default
(second order, one force evaluation per step). The solver keeps no state of its own between
calls but the accelerations of the last step, which velocity Verlet reuses: the state is the
coordinates, their first and second derivatives and the data coordinates (limit stops), and
restoring it makes the next steps bit-identical (one thread, contact cells never re-created).
"""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass, field

import exudyn as exu
import numpy as np
from exudyn.itemInterface import (
    LoadMassProportional,
    LoadTorqueVector,
    MarkerBodyMass,
    MarkerBodyPosition,
    MarkerBodyRigid,
    MarkerKinematicTreeRigid,
    MarkerNodeCoordinate,
    NodeGenericData,
    NodeGenericODE2,
    NodePointGround,
    NodeRigidBodyRotVecLG,
    ObjectConnectorCoordinateSpringDamperExt,
    ObjectGround,
    ObjectKinematicTree,
    ObjectRigidBody,
)

from dynabrain.orchestrator.kernel.core import Edits

from . import cable as xc
from . import contact as xk
from . import geometry as geo
from . import joints as xj
from .inputs import Inputs
from .outputs import Frame, Outputs
from .plan import Carrier, Plan
from .topology import Topology
from .tree import Kinematics, TreeSpec

INTEGRATORS = {"velocity_verlet": "VelocityVerlet", "rk44": "RK44", "explicit_midpoint": "ExplicitMidpoint",
               "explicit_euler": "ExplicitEuler", "rk33": "RK33"}
LIMIT_ZETA = 1.0
"""Damping ratio of joint limit stops (no bounce)."""


_QUIET_LOCK = threading.Lock()
_quiet = {"depth": 0, "saved": True}


@contextlib.contextmanager
def quiet(verbose: bool):
    """Exudyn prints warnings to the console; the core prints nothing unless asked (``verbose``).
    Exudyn's switch is global: nested and concurrent uses (forks stepping in threads) share it, and the
    last one out puts back what was there."""
    if verbose:
        yield
        return
    with _QUIET_LOCK:
        if _quiet["depth"] == 0:
            _quiet["saved"] = exu.config.printToConsole
            exu.config.printToConsole = False
        _quiet["depth"] += 1
    try:
        yield
    finally:
        with _QUIET_LOCK:
            _quiet["depth"] -= 1
            if _quiet["depth"] == 0:
                exu.config.printToConsole = _quiet["saved"]


@dataclass
class Start:
    """Where a structure starts: world poses and velocities of bodies, joint values, cable coordinates."""

    pose: dict[str, geo.Pose] = field(default_factory=dict)
    vel: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    q: dict[str, float] = field(default_factory=dict)
    qd: dict[str, float] = field(default_factory=dict)
    cables: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


@dataclass(frozen=True)
class Options:
    """What a system is built with and cannot change: the integrator, whether Exudyn may print, and
    whether the links of kinematic trees have contact geometry (each sphere on a link costs a forward
    kinematics a step: a chain that touches nothing runs three to four times faster without)."""

    integrator: str = "velocity_verlet"
    verbose: bool = False
    link_contacts: bool = True


class System(Outputs, Inputs):
    """An Exudyn system for one structure (a `Plan`), ready to step."""

    def __init__(self, top: Topology, plan: Plan, edits: Edits, start: Start, options: Options, settings: dict,
                 own: frozenset[str] = frozenset()):
        self.top, self.plan, self.edits, self._start = top, plan, edits, start
        self.own = own  # the bodies with friction or restitution of their own: a material each
        self.options, self.verbose = options, options.verbose
        self.sc = exu.SystemContainer()
        self.mbs = mbs = self.sc.AddSystem()
        self.ground = mbs.AddObject(ObjectGround())
        self.ground_marker = mbs.AddMarker(MarkerBodyRigid(bodyNumber=self.ground))
        self.frames: dict[str, Frame] = {}
        self.items: list[xk.BodyItems] = []
        self.materials: list[float | None] = [None]
        self.free: list[tuple[int, int, int]] = []  # (node, rigid body, gravity load)
        self.free_mass: list[float] = []  # the mass of each free carrier
        self.free_inertia: list[np.ndarray] = []  # ... and its inertia about its centre of mass (3x3)
        self.torque_loads: list[int] = []  # each free carrier's torque load (`Inputs.push`)
        self.trees: list[dict] = []
        self.cables: list[xc.CableParts] = []
        self.limits: list[tuple[int, float]] = []  # (connector, inertia about the joint)
        self.joint_index: dict[str, tuple[int, int]] = {}  # joint -> (tree, coordinate in tree)
        self.link_ref: list[tuple[int, int]] = []  # global link -> (kinematic tree object, link in it)
        with quiet(self.verbose):
            for owner in ("", *(n for n in top.bodies if n in plan.carriers and n)):
                self._carrier(plan.carriers[owner], start)
            for cable in self.cables:
                xc.pin(self, cable)
            self.springs = xj.build(self, plan.joints)
            excluded = self._excluded(plan.groups)
            self.wn = float(settings["wn"])
            self.contacts = xk.build_sets(mbs, self.items, excluded, self._box(), len(self.materials), self.wn)
            mbs.Assemble()
            self.pushed = np.zeros((len(self.free), 6))  # the free carriers' wrenches (`Inputs.push`)
            self.pushing = False  # whether any is not zero
            self.apply(**settings)  # before the solver starts: it computes the first accelerations
            self._solver(options.integrator)
        self._index_outputs()
        self._index_inputs()

    # -- building -------------------------------------------------------------------------------------------
    def _carrier(self, c: Carrier, start: Start) -> None:
        if c.kind == "world":
            for body, x in c.members.items():
                self.frames[body] = Frame("world", 0, x)
                if body not in self.plan.absent:  # (an absent body: no contact geometry, nothing to compute)
                    self._items(body, "world", x, 0.0, self.ground, None)
        elif c.kind == "free":
            self._free(c, start)
        elif c.kind == "link":
            if self.top.tree_of[c.owner] == c.owner:
                self._tree(c.owner, start)
        else:
            parts = xc.build(self, c, start)
            self.frames[c.owner] = (Frame("world", 0, xc.tip_pose(parts.coords)) if parts.frozen
                                    else Frame("cable", len(self.cables), geo.IDENTITY))
            self.cables.append(parts)

    def _mass(self, members: dict[str, geo.Pose]) -> tuple[float, np.ndarray, np.ndarray]:
        parts = []
        for body, x in members.items():
            b = self.top.spec[body]
            m, inertia, centre = geo.body_mass(b)
            if m > 0:
                rot = geo.quat_to_mat(x[1])
                parts.append((m, inertia, x[0] + rot @ centre, rot))
        return geo.combine(parts)

    def _free(self, c: Carrier, start: Start) -> None:
        mass, com, inertia = self._mass(c.members)
        x_wo = start.pose.get(c.owner, self.top.world[c.owner])
        x_wn = geo.compose(x_wo, (com, geo.IDENTITY[1]))
        lin, ang = start.vel.get(c.owner, (np.zeros(3), np.zeros(3)))
        r_wn = geo.quat_to_mat(x_wn[1])
        v_node = lin + np.cross(ang, r_wn @ com)
        mbs = self.mbs
        node = mbs.AddNode(NodeRigidBodyRotVecLG(
            referenceCoordinates=[0.0] * 6, initialCoordinates=[*x_wn[0], *geo.quat_to_rotvec(x_wn[1])],
            initialVelocities=[*v_node, *(r_wn.T @ ang)]))
        body = mbs.AddObject(ObjectRigidBody(mass=mass, nodeNumber=node, inertia=[
            inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[1, 2], inertia[0, 2], inertia[0, 1]]))
        load = mbs.AddLoad(LoadMassProportional(markerNumber=mbs.AddMarker(MarkerBodyMass(bodyNumber=body)),
                                                   loadVector=[0.0, 0.0, 0.0]))
        self.free.append((node, body, load))
        self.free_mass.append(mass)
        self.free_inertia.append(np.asarray(inertia, dtype=float))
        self.torque_loads.append(mbs.AddLoad(LoadTorqueVector(  # world frame (`Inputs.push`)
            markerNumber=mbs.AddMarker(MarkerBodyRigid(bodyNumber=body)), loadVector=[0.0, 0.0, 0.0])))
        shift = (-com, geo.IDENTITY[1])
        for member, x in c.members.items():
            x_nb = geo.compose(shift, x)
            self.frames[member] = Frame("free", len(self.free) - 1, x_nb)
            self._items(member, "free", x_nb, mass, body, None)

    def _tree(self, root: str, start: Start) -> None:
        top, mbs = self.top, self.mbs
        links = self.plan.trees[root]
        spec = TreeSpec(top, self.plan, links, self._mass)
        q0 = [start.q.get(j, self.plan.frozen_joints.get(j, 0.0)) for j in spec.joints]
        qd0 = [start.qd.get(j, 0.0) for j in spec.joints]
        n = len(links)
        node = mbs.AddNode(NodeGenericODE2(referenceCoordinates=[0.0] * n, initialCoordinates=q0,
                                              initialCoordinates_t=qd0, numberOfODE2Coordinates=n))
        kt = mbs.AddObject(ObjectKinematicTree(
            nodeNumber=node, jointTypes=spec.kinds, linkParents=spec.parents,
            jointTransformations=exu.Matrix3DList(spec.rotations), jointOffsets=exu.Vector3DList(spec.offsets),
            linkInertiasCOM=exu.Matrix3DList(spec.inertias), linkCOMs=exu.Vector3DList(spec.coms),
            linkMasses=spec.masses, gravity=[0.0, 0.0, 0.0], jointForceVector=[0.0] * n,
            jointDControlVector=spec.damping, jointVelocityOffsetVector=[0.0] * n))
        first = sum(len(t["links"]) for t in self.trees)
        markers = []
        for i, link in enumerate(links):
            markers.append(mbs.AddMarker(MarkerKinematicTreeRigid(objectNumber=kt, linkNumber=i,
                                                                     localPosition=[0.0, 0.0, 0.0])))
            self.joint_index[spec.joints[i]] = (len(self.trees), i)
            for member, x in spec.members[i].items():
                self.frames[member] = Frame("link", first + i, x)
                if self.options.link_contacts:
                    self._items(member, "link", x, spec.masses[i], kt, (i, markers[i]))
            self._limit(node, i, top.spec[link], spec.axis_inertia(i, top.spec[link].joint.kind))
        self.trees.append({"kt": kt, "node": node, "links": links, "markers": markers, "joints": spec.joints,
                           "kinematics": Kinematics(spec), "spec": spec})
        self.link_ref += [(kt, i) for i in range(n)]

    def _limit(self, node: int, i: int, b, inertia: float) -> None:
        """A limit stop for a joint with a range (its stiffness and damping follow the contact parameters)."""
        if b.joint.range is None:
            return
        mbs = self.mbs
        ground_node = mbs.AddNode(NodePointGround())
        lo, hi = (float(x) for x in b.joint.range)
        connector = mbs.AddObject(ObjectConnectorCoordinateSpringDamperExt(
            markerNumbers=[mbs.AddMarker(MarkerNodeCoordinate(nodeNumber=ground_node, coordinate=0)),
                           mbs.AddMarker(MarkerNodeCoordinate(nodeNumber=node, coordinate=i))],
            nodeNumber=mbs.AddNode(NodeGenericData(numberOfDataCoordinates=3, initialCoordinates=[0.0] * 3)),
            stiffness=0.0, damping=0.0, useLimitStops=True, limitStopsLower=lo, limitStopsUpper=hi,
            limitStopsStiffness=0.0, limitStopsDamping=0.0, frictionProportionalZone=1e-3))
        self.limits.append((connector, inertia))

    def _items(self, body: str, kind: str, x: geo.Pose, mass: float, exu_body: int, link) -> None:
        b = self.top.spec[body]
        if b.shape not in geo.SHAPES_WITH_CONTACT:
            return
        shape = geo.body_contact_shape(b)
        rot = geo.quat_to_mat(x[1])
        centers = shape.centers @ rot.T + x[0]
        item = xk.BodyItems(body, mass, shape.support, shape.round, self.material(body), static=kind == "world")
        for c, r in zip(centers, shape.radii, strict=False):
            item.spheres.append((self._marker(kind, exu_body, link, c), float(r)))
        if len(shape.triangles):
            marker = {"world": self.ground_marker, "link": link[1] if link else None}.get(kind)
            marker = marker if marker is not None else self._marker(kind, exu_body, link, np.zeros(3))
            item.mesh = (marker, shape.points @ rot.T + x[0], shape.triangles)
        self.items.append(item)

    def material(self, body: str) -> int:
        """The friction material of a body: 0 (the core's coefficients) or one of its own (its values
        are set by `apply`)."""
        if body not in self.own:
            return 0
        self.materials.append(body)
        return len(self.materials) - 1

    def _body_point(self, target: str, point: np.ndarray) -> tuple[Frame, np.ndarray]:
        """A body's carrier frame and the body-fixed point that was at world ``point`` at t=0, in it."""
        local = geo.inverse(self.top.world[target])
        p_body = geo.compose(local, (point, geo.IDENTITY[1]))[0]
        frame = self.frames[target]
        return frame, geo.compose(frame.pose, (p_body, geo.IDENTITY[1]))[0]

    def point_marker(self, target: str, point: np.ndarray) -> int | None:
        """A marker on the moving carrier of ``target`` at its point that was at ``point`` at t=0; None
        when the target does not move (the world, a static or frozen body)."""
        if target == "world" or self.frames[target].kind == "world":
            return None
        frame, local = self._body_point(target, point)
        if frame.kind == "free":
            body = self.free[frame.index][1]
            return self.mbs.AddMarker(MarkerBodyPosition(bodyNumber=body, localPosition=list(map(float, local))))
        kt, link = self.link_ref[frame.index]
        return self.mbs.AddMarker(MarkerKinematicTreeRigid(objectNumber=kt, linkNumber=link,
                                                              localPosition=list(map(float, local))))

    def world_marker(self, target: str, point: np.ndarray) -> int:
        """A ground marker where the point of a static ``target`` is (``point`` itself for the world)."""
        where = point if target == "world" else self._body_point(target, point)[1]
        return self.mbs.AddMarker(MarkerBodyPosition(bodyNumber=self.ground, localPosition=list(map(float, where))))

    def _marker(self, kind: str, exu_body: int, link, local: np.ndarray) -> int:
        if kind == "link":
            return self.mbs.AddMarker(MarkerKinematicTreeRigid(objectNumber=exu_body, linkNumber=link[0],
                                                                  localPosition=list(map(float, local))))
        return self.mbs.AddMarker(MarkerBodyRigid(bodyNumber=exu_body, localPosition=list(map(float, local))))

    def _excluded(self, groups: tuple) -> dict[str, set[str]]:
        """Body -> bodies it does not touch: the `no_collision` groups (with subtrees), and the bodies of
        one kinematic tree among themselves (Exudyn skips a sphere against triangles of the same tree
        already, but not two spheres: neighbouring links' spheres overlap at their joint)."""
        excluded: dict[str, set[str]] = {}
        for tree in self.trees:
            bodies = {m for link in tree["links"] for m in self.plan.carriers[link].members}
            for a in bodies:
                excluded.setdefault(a, set()).update(bodies - {a})
        for group in groups:
            trees = [set(self.top.subtree[n]) for n in group]
            for i, ta in enumerate(trees):
                for tb in trees[:i] + trees[i + 1:]:
                    for a in ta:
                        excluded.setdefault(a, set()).update(tb - {a})
        return excluded

    def _box(self) -> tuple[np.ndarray, np.ndarray]:
        """The contact search box: everything there is at the start (infinite planes left out), with margins."""
        points = [np.zeros((1, 3))] + [self._start.pose.get(b, self.top.world[b])[0].reshape(1, 3)
                                       for b in self.top.bodies]
        for it in self.items:
            if it.mesh is not None and np.abs(it.mesh[1]).max() < geo.PLANE_HALF:
                points.append(it.mesh[1])
        allp = np.vstack(points)
        low, high = allp.min(axis=0), allp.max(axis=0)
        margin = 1.0 + 0.5 * (high - low)
        return low - margin, high + margin

    def _solver(self, integrator: str) -> None:
        ss = self.settings = exu.SimulationSettings()
        ti = ss.timeIntegration
        ti.solverType = getattr(exu.DynamicSolverType, INTEGRATORS[integrator])
        ti.numberOfSteps, ti.endTime, ti.verboseMode = 1, 1e-3, 0
        ti.explicit.useLieGroupIntegration = True
        ti.explicit.eliminateConstraints = True
        ss.solution.file.write = False
        ss.solution.sensors.active = False
        ss.solution.restart.write = False
        ss.solution.file.writeFooter = False
        ss.parallel.numberOfThreads = 1
        ss.show.statistics = False
        ss.show.computationTime = False
        self.solver = exu.MainSolverExplicit()
        if not self.solver.InitializeSolver(self.mbs, ss):
            raise RuntimeError("Exudyn could not initialise its solver")

    @property
    def lightest(self) -> float:
        """The smallest mass that moves on its own: a carrier's, or a cable node's share."""
        masses = [it.mass / (it.support if self.top.role.get(it.body) == "cable" else 1)
                  for it in self.items if not it.static and it.mass > 0]
        return min(masses, default=1.0)

    def apply(self, *, gravity: np.ndarray, wn: float, zeta: float, friction_zone: float, friction: float,
              step: float, own: dict | None = None) -> None:
        """Apply run-time parameters (idempotent; the contact frequency must be the one it was built with)."""
        mbs, g = self.mbs, [float(x) for x in gravity]
        self.gravity = g
        for i, (_node, _body, load) in enumerate(self.free):
            mbs.SetLoadParameter(load, "loadVector", self.gravity_load(i))
        for tree in self.trees:
            mbs.SetObjectParameter(tree["kt"], "gravity", g)
        for cable in self.cables:
            for load in cable.loads:
                mbs.SetLoadParameter(load, "loadVector", g)
        for connector, inertia in self.limits:
            mbs.SetObjectParameter(connector, "limitStopsStiffness", inertia * wn * wn)
            mbs.SetObjectParameter(connector, "limitStopsDamping", 2.0 * LIMIT_ZETA * wn * inertia)
        own = own or {}
        xk.apply(self.contacts, wn=wn, zeta=zeta, friction_zone=friction_zone,
                 pairings=xk.pairings(friction, [None] + [own.get(b, (None, None))[0] for b in self.materials[1:]]),
                 step=step, lightest=self.lightest, zetas={b: z for b, (_f, z) in own.items() if z is not None})
        xj.apply(self, self.springs, wn)

    def set_forces(self, force: np.ndarray) -> None:
        for tree, rows in zip(self.trees, self.force_rows, strict=True):
            self.mbs.SetObjectParameter(tree["kt"], "jointForceVector", force[rows])

    # -- state and stepping ----------------------------------------------------------------------------------
    def get_state(self) -> np.ndarray:
        sd = self.mbs.systemData
        return np.concatenate([sd.GetODE2Coordinates(), sd.GetODE2Coordinates_t(), sd.GetODE2Coordinates_tt(),
                               sd.GetDataCoordinates()])

    def set_state(self, state: np.ndarray) -> None:
        sd = self.mbs.systemData
        n = sd.ODE2Size()
        sd.SetODE2Coordinates(state[:n])
        sd.SetODE2Coordinates_t(state[n:2 * n])
        sd.SetODE2Coordinates_tt(state[2 * n:3 * n])
        sd.SetDataCoordinates(state[3 * n:])
        self.read()

    def step(self, t0: float, t1: float, substeps: int) -> None:
        it = self.solver.it
        it.currentTime, it.endTime, it.maxStepSize = t0, t1, (t1 - t0) / substeps
        self.solver.it = it
        with quiet(self.verbose):
            self.solver.SolveSteps(self.mbs, self.settings)
        self.read()

    def place(self, body: str, target: geo.Pose) -> None:
        """Put the free carrier of ``body`` so that ``body`` is at ``target``, at rest."""
        frame = self.frames[body]
        x_wn = geo.compose(target, geo.inverse(frame.pose))
        sd = self.mbs.systemData
        x, v = sd.GetODE2Coordinates(), sd.GetODE2Coordinates_t()
        k = self.free_index[frame.index] + np.arange(6)
        x[k] = [*x_wn[0], *geo.quat_to_rotvec(x_wn[1])]
        v[k] = 0.0
        sd.SetODE2Coordinates(x)
        sd.SetODE2Coordinates_t(v)
        self.read()
