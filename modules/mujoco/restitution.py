"""Contact parameters from a coefficient of restitution, for the MuJoCo core.

All contacts use a soft contact of constant impedance ``IMPEDANCE`` whose stiffness and damping are given
directly (MuJoCo's negative ``solref``): natural frequency ``wn`` (see `contact_frequency`) and damping
``2 zeta wn``. The damping ratio ``zeta`` of a restitution ``e`` is calibrated once per (timestep, wn,
gravity) by bouncing a one-dof sphere in MuJoCo itself for a grid of damping ratios and inverting that
curve (`damping_ratio`).
"""

from __future__ import annotations

import threading

import mujoco
import numpy as np

from . import options

IMPEDANCE = 0.99
"""Constant constraint impedance of contacts (solimp d0 = dwidth): contacts follow their reference
acceleration to 99 %, which keeps the effective stiffness and damping those of the solref."""
FREQ_PER_STEP = 0.1
"""Contact natural frequency times timestep: ~60 steps per contact oscillation."""
FREQ_MAX = 800.0
"""Upper bound of the contact natural frequency (rad/s) reached with small timesteps."""
CALIBRATION_SPEED = 1.5
"""Impact speed (m/s) at which the restitution is calibrated (a drop of about 11 cm)."""
_ZETAS = np.array([0.0, 0.02, 0.05, 0.08, 0.12, 0.17, 0.23, 0.3, 0.4, 0.5, 0.62, 0.75, 0.9, 1.0,
                   1.25, 1.5, 2.0, 3.0, 4.0])

_CALIBRATION: dict[tuple[float, float, float], np.ndarray] = {}
_TINY: list[tuple[mujoco.MjModel, mujoco.MjData]] = []
_LOCK = threading.Lock()  # forks may step in threads; the calibration model is shared


def contact_frequency(dt: float) -> float:
    """Natural frequency (rad/s) of contacts at engine timestep ``dt``."""
    return min(FREQ_PER_STEP / dt, FREQ_MAX)


def contact_params(restitution: float, dt: float, gravity: float) -> tuple[np.ndarray, np.ndarray]:
    """(solref, solimp) of every contact for a coefficient of restitution."""
    wn = contact_frequency(dt)
    zeta = damping_ratio(restitution, dt, wn, gravity)
    solref = np.array([-wn * wn, -2.0 * zeta * wn])
    solimp = np.array([IMPEDANCE, IMPEDANCE, 0.001, 0.5, 2.0])
    return solref, solimp


def damping_ratio(e: float, dt: float, wn: float, gravity: float) -> float:
    """The damping ratio whose measured restitution is ``e`` (calibrated, cached)."""
    key = (float(dt), float(wn), round(float(gravity), 9))
    with _LOCK:
        if key not in _CALIBRATION:
            _CALIBRATION[key] = np.minimum.accumulate(_calibrate(*key))
        measured = _CALIBRATION[key]
    if e <= 0.0:  # no bounce: 1.5 times the least damping that stops the calibration bounce
        stuck = np.flatnonzero(measured <= 0.0)
        return float(min(max(1.0, 1.5 * _ZETAS[stuck[0]]), _ZETAS[-1]) if len(stuck) else _ZETAS[-1])
    if e >= measured[0]:
        return 0.0
    return float(np.interp(-e, -measured, _ZETAS))


def _tiny() -> tuple[mujoco.MjModel, mujoco.MjData]:
    """A sphere of radius 0.1 on a slide joint over a plane, with the core's contact options."""
    if not _TINY:
        spec = mujoco.MjSpec()
        options.apply(spec, {})
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1])
        ball = spec.worldbody.add_body(name="ball")
        ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.1, 0, 0], mass=1.0)
        ball.add_joint(type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1])
        model = spec.compile()
        model.geom_solimp[:] = [IMPEDANCE, IMPEDANCE, 0.001, 0.5, 2.0]
        _TINY.append((model, mujoco.MjData(model)))
    return _TINY[0]


def _calibrate(dt: float, wn: float, gravity: float, phases: int = 3) -> np.ndarray:
    """Measured restitution for each damping ratio of ``_ZETAS`` (mean over impact phases)."""
    model, data = _tiny()
    model.opt.timestep = dt
    model.opt.gravity[:] = (0.0, 0.0, -gravity)
    v = CALIBRATION_SPEED
    limit = int(8 * np.pi / (wn * dt)) + 20
    out = np.zeros(len(_ZETAS))
    for k, zeta in enumerate(_ZETAS):
        model.geom_solref[:] = (-wn * wn, -2.0 * zeta * wn)
        for p in range(phases):
            z0 = 0.1 + (p + 0.5) / phases * v * dt
            mujoco.mj_resetData(model, data)
            data.qpos[0], data.qvel[0] = z0, -v
            out[k] += _bounce(model, data, z0, v, gravity, limit) / phases
    return out


def _bounce(model, data, z0: float, v: float, gravity: float, limit: int) -> float:
    touched = False
    for _ in range(limit):
        mujoco.mj_step(model, data)
        if data.ncon:
            touched = True
        elif touched and data.qvel[0] > 0:
            vz = data.qvel[0]
            return float(np.sqrt(max(vz * vz + 2 * gravity * (data.qpos[0] - z0), 0.0)) / v)
    return 0.0
