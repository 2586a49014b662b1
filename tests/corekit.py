"""Driving a physics core directly (no World), for the core tests: ports are bound by a small helper that
allocates every block port and views for the ``view_of`` ports, as the kernel does."""

from __future__ import annotations

import numpy as np

from dynabrain.orchestrator.kernel.core import BodySpec, JointSpec, PhysicsCore, SceneSpec
from dynabrain.orchestrator.kernel.module import PortBinding, SetupContext

DT = 2_000_000
G = 9.81
FLOOR = BodySpec("floor", "plane", ())


def bind(core: PhysicsCore) -> tuple[dict, dict]:
    """Lay the ports out like the kernel (each direction's own ports in a row of one flat buffer,
    the ``view_of`` ports as views into them, each at its start value), then bind the core."""
    bound: list = [{}, {}]
    flats = []
    for ports, dst in zip((core.inputs(), core.outputs()), bound, strict=True):
        own = [p for p in ports if p.view_of is None]
        flat = np.zeros(sum(p.size for p in own))
        at = 0
        for p in own:
            dst[p.name] = flat[at:at + p.size].reshape(p.shape)
            if p.start is not None:
                dst[p.name][...] = p.start
            at += p.size
        for p in ports:
            if p.view_of is not None:
                base, at = dst[p.view_of[0]], p.view_of[1]
                view = (base[at:at + p.size] if base.ndim == 1 else base[at]).reshape(p.shape)
                assert np.shares_memory(view, base), p.name
                dst[p.name] = view
        flats.append(flat)
    inp, out = bound
    core.bind_ports(PortBinding(inp, out, flats[0], flats[1]))
    core.bind()
    return inp, out


def make_core(cls: type[PhysicsCore], *bodies: BodySpec, model: str | None = None, **params):
    """A core of class ``cls`` on a scene of ``bodies`` (or a model file), set up, bound and started."""
    core = cls("phys", SceneSpec(bodies=bodies, model=model), **params)
    core.setup(SetupContext(world_name="t", dt_ns=DT, period_ns=DT, tick=0, rng=np.random.default_rng(0)))
    inp, out = bind(core)
    core.start(0)
    return core, inp, out


def run(core: PhysicsCore, n: int, record: str | None = None, out: dict | None = None, t0: int = 0) -> list:
    """``n`` steps from ``t0``; the values of output ``record`` after each."""
    frames = []
    for i in range(n):
        core.step(t0 + i * DT, DT)
        if record is not None:
            frames.append(np.array(out[record]))
    return frames


def trajectory(core: PhysicsCore, out: dict, n: int, t0: int = 0) -> np.ndarray:
    """``n`` steps; every body pose and velocity and every joint after each, one row a step."""
    frames = []
    for i in range(n):
        core.step(t0 + i * DT, DT)
        frames.append(np.concatenate([out["body_pos"].ravel(), out["body_quat"].ravel(),
                                      out["body_linvel"].ravel(), out["joint_q"], out["joint_qd"]]))
    return np.array(frames)


def box(name, size, pos, **kw) -> BodySpec:
    return BodySpec(name, "box", size, pos=pos, **kw)


def scene_for_state() -> tuple[BodySpec, ...]:
    """Three boxes (one tumbling) and a hinged arm over a floor."""
    return (FLOOR, box("a", (0.1, 0.1, 0.1), (0, 0, 0.3), mass=0.05),
            box("b", (0.1, 0.1, 0.1), (0.3, 0, 0.2), mass=0.05),
            box("c", (0.1, 0.1, 0.1), (0.02, 0.01, 0.6), quat=(0.96, 0.2, 0.1, 0.17), mass=0.05),
            BodySpec("arm", "capsule", (0.02, 0.4), pos=(1, 0, 1),
                     joint=JointSpec("hinge", axis=(0, 1, 0), anchor=(0, 0, 0.2), damping=0.01)))
