"""Restitution of the Exudyn core's contacts, calibrated in Exudyn itself.

A linear spring-damper contact that may pull until it separates bounces with
``e = exp(-zeta pi / sqrt(1 - zeta^2))``; under gravity, and integrated with a finite step, a bounce
comes out lower (gravity brakes the rebound while the contact lasts). As the MuJoCo core does, the
core measures it: a sphere dropped at ``CALIBRATION_SPEED`` onto a plane, with the core's contact
frequency, step, gravity and integrator, for a grid of damping ratios (averaged over where in a step
the impact falls), and inverts that curve. The table is cached per (step, frequency, gravity,
integrator); making one takes a few tens of milliseconds.
"""

from __future__ import annotations

import math
import threading

import exudyn as exu
import numpy as np
from exudyn.itemInterface import (
    LoadMassProportional,
    MarkerBodyMass,
    MarkerBodyRigid,
    NodeRigidBodyRotVecLG,
    ObjectGround,
    ObjectRigidBody,
)

CALIBRATION_SPEED = 1.5
"""Impact speed (m/s) at which restitution is calibrated (a drop of about 11 cm)."""
ZETAS = np.array([0.0, 0.02, 0.05, 0.08, 0.12, 0.17, 0.23, 0.3, 0.4, 0.5, 0.62, 0.75, 0.9, 1.0])
PHASES = 6
RADIUS = 0.1
_TABLES: dict[tuple, np.ndarray] = {}
_LOCK = threading.Lock()  # forks may step in threads


def zeta_for(restitution: float, step: float, wn: float, gravity: float, integrator: str) -> float:
    """The damping ratio whose measured bounce has coefficient ``restitution`` (0 gives 1: critical)."""
    if restitution <= 0.0:
        return 1.0
    key = (float(step), float(wn), round(float(gravity), 9), integrator)
    with _LOCK:
        if key not in _TABLES:
            _TABLES[key] = np.minimum.accumulate(_measure(*key))
        measured = _TABLES[key]
    if restitution >= measured[0]:
        return 0.0
    if restitution <= measured[-1]:
        return float(ZETAS[-1])
    return float(np.interp(-restitution, -measured, ZETAS))


def _measure(step: float, wn: float, gravity: float, integrator: str) -> np.ndarray:
    from .system import INTEGRATORS, quiet  # the solver settings the core uses

    with quiet(False):
        sc = exu.SystemContainer()
        mbs = sc.AddSystem()
        ground = mbs.AddMarker(MarkerBodyRigid(bodyNumber=mbs.AddObject(ObjectGround())))
        node = mbs.AddNode(NodeRigidBodyRotVecLG(referenceCoordinates=[0.0] * 6,
                                                 initialCoordinates=[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))
        body = mbs.AddObject(ObjectRigidBody(mass=1.0, inertia=[0.004] * 3 + [0.0] * 3, nodeNumber=node))
        mbs.AddLoad(LoadMassProportional(markerNumber=mbs.AddMarker(MarkerBodyMass(bodyNumber=body)),
                                         loadVector=[0.0, 0.0, -gravity]))
        gc = mbs.AddGeneralContact()
        gc.keepContactWhilePenetrating = True
        gc.SetFrictionPairings(np.zeros((1, 1)))
        gc.AddTrianglesRigidBodyBased(rigidBodyMarkerIndex=ground, contactStiffness=1e12, contactDamping=0.0,
                                      frictionMaterialIndex=0, triangleList=[[0, 1, 2], [0, 2, 3]],
                                      pointList=[[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], staticTriangles=True)
        sphere = gc.AddSphereWithMarker(mbs.AddMarker(MarkerBodyRigid(bodyNumber=body)), radius=RADIUS,
                                        contactStiffness=wn * wn, contactDamping=0.0, frictionMaterialIndex=0)
        gc.SetSearchTreeCellSize([1, 1, 1])
        gc.SetSearchTreeBox([-2, -2, -1], [2, 2, 3])
        mbs.Assemble()
        ss = exu.SimulationSettings()
        ss.timeIntegration.solverType = getattr(exu.DynamicSolverType, INTEGRATORS[integrator])
        ss.timeIntegration.explicit.useLieGroupIntegration = True
        ss.timeIntegration.numberOfSteps, ss.timeIntegration.endTime = 1, step
        ss.solution.file.write = False
        ss.solution.sensors.active = False
        ss.solution.restart.write = False
        ss.parallel.numberOfThreads = 1
        solver = exu.MainSolverExplicit()
        solver.InitializeSolver(mbs, ss)
        steps = math.ceil(2.0 * math.pi / (wn * step)) + 4  # the contact (up to zeta ~ 0.85), then free flight
        out = np.zeros(len(ZETAS))
        for k, zeta in enumerate(ZETAS):
            gc.SetSphereMarkerBased(sphere, contactDamping=2.0 * zeta * wn)
            for p in range(PHASES):
                out[k] += _bounce(mbs, solver, ss, step, steps, gravity, (p + 0.5) / PHASES) / PHASES
    return out


def _bounce(mbs, solver, ss, step: float, steps: int, gravity: float, phase: float) -> float:
    v = CALIBRATION_SPEED
    z0 = RADIUS + phase * v * step
    sd = mbs.systemData
    sd.SetODE2Coordinates([0.0, 0.0, z0, 0.0, 0.0, 0.0])
    sd.SetODE2Coordinates_t([0.0, 0.0, -v, 0.0, 0.0, 0.0])
    sd.SetODE2Coordinates_tt([0.0, 0.0, -gravity, 0.0, 0.0, 0.0])
    it = solver.it
    it.currentTime, it.endTime, it.maxStepSize = 0.0, steps * step, step
    solver.it = it
    solver.SolveSteps(mbs, ss)
    z, vz = sd.GetODE2Coordinates()[2], sd.GetODE2Coordinates_t()[2]
    if z <= RADIUS:  # still in contact: it does not bounce (or too little to leave in a contact period)
        return 0.0
    v_in = math.sqrt(v * v + 2.0 * gravity * (z0 - RADIUS))
    return math.sqrt(vz * vz + 2.0 * gravity * (z - RADIUS)) / v_in
