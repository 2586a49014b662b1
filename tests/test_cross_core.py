"""The two cores agree: the same scenes, run by MuJoCo and by Exudyn, move alike within tolerances
that come from what each engine does differently (stated at each test).

The main differences: MuJoCo integrates with a semi-implicit Euler step (first order: its position
error grows as g h t / 2 in free fall) at the world's 2 ms, Exudyn with velocity Verlet (second order)
at 0.5 ms; MuJoCo's contacts are soft constraints, Exudyn's penalty springs (mass-scaled, see
`dynabrain.modules.exudyn.contact`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynabrain.modules.exudyn.core import ExudynCore
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator.kernel.core import BodySpec, JointSpec, SceneSpec
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
CORES = (MujocoCore, ExudynCore)
G = 9.81
H = 0.002


def world(cls, *bodies: BodySpec, **params) -> World:
    return World(cls.ENGINE, step="2ms", core=cls("core", SceneSpec(bodies=bodies), **params))


def record(w: World, n: int, names: list[str]) -> np.ndarray:
    out = []
    for _ in range(n):
        w.tick()
        out.append(np.concatenate([np.ravel(w.get(name)) for name in names]))
    return np.array(out)


def test_free_fall_agrees_within_mujocos_integration_error():
    runs = {cls.ENGINE: record(world(cls, BodySpec("ball", "sphere", (0.05,), pos=(0, 0, 10.0), mass=1.0)),
                               250, ["ball.pos", "ball.linvel"]) for cls in CORES}
    t = H * np.arange(1, 251)
    exact = 10.0 - G * t * t / 2
    # Exudyn's velocity Verlet is exact for a constant force; MuJoCo's semi-implicit Euler lies
    # g h t / 2 lower (4.9 mm after 0.5 s): the cores differ by exactly that, and agree on velocities
    assert np.abs(runs["exudyn"][:, 2] - exact).max() < 1e-9
    assert np.abs(runs["exudyn"][:, 2] - runs["mujoco"][:, 2] - G * H * t / 2).max() < 1e-9
    assert np.abs(runs["exudyn"][:, 3:] - runs["mujoco"][:, 3:]).max() < 1e-9


def period(q: np.ndarray) -> float:
    up = np.flatnonzero((q[:-1] < 0) & (q[1:] >= 0))
    frac = up + (-q[up] / (q[up + 1] - q[up]))
    return float((frac[-1] - frac[0]) / (len(frac) - 1) * H)


def test_pendulum_period_agrees():
    length, periods = 0.5, {}
    for cls in CORES:
        w = world(cls, BodySpec("bob", "sphere", (0.01,), pos=(0, 0, 1.0), mass=1.0,
                                joint=JointSpec("hinge", axis=(0, 1, 0), anchor=(0, 0, length))))
        w.set("core.bob.force", 2.0)
        w.tick(10)
        w.set("core.bob.force", 0.0)
        periods[cls.ENGINE] = period(record(w, 2500, ["bob.q"])[:, 0])
        w.close()
    exact = 2 * np.pi * np.sqrt((length**2 + 0.4 * 0.01**2) / (G * length))
    # amplitude 0.036 rad adds theta^2 / 16 = 8e-5 to the period; both integrators' period errors are
    # O((w h)^2) ~ 1e-5: each within 2e-4 of the exact period, and of each other
    for p in periods.values():
        assert p == pytest.approx(exact, rel=2e-4)
    assert periods["exudyn"] == pytest.approx(periods["mujoco"], rel=2e-4)


def chain(core: str, substeps: int = 0) -> np.ndarray:
    w = load_scenario(SCENARIOS / "pendulum_chain.yaml").build(core=core)
    if substeps:
        w.set("core.substeps", substeps)
    out = record(w, 1000, ["l1.pos", "l2.pos", "l3.pos", "l4.pos"])
    w.close()
    return out


def test_chain_motion_agrees_and_the_difference_is_mujocos_step():
    exudyn = chain("exudyn")
    coarse = np.abs(chain("mujoco") - exudyn).max()
    fine = np.abs(chain("mujoco", substeps=4) - exudyn).max()
    # four links whipping down from horizontal for 2 s: the link positions differ by 3 mm at most, and
    # the difference is MuJoCo's first-order integration error: a 4 times smaller MuJoCo step makes it
    # about 4 times smaller (measured 3.2 mm, then 0.7 mm)
    assert coarse < 5e-3
    assert fine < 0.35 * coarse


def arm(core: str, substeps: int = 0) -> np.ndarray:
    w = load_scenario(SCENARIOS / "robot_arm.yaml").build(core=core)
    if substeps:
        w.set("core.substeps", substeps)
    out = record(w, 125, ["core.joint_q", "hand.pos"])  # 0.25 s: before the hand reaches the crate
    w.close()
    return out


def test_robot_arm_moves_alike_until_it_touches_the_crate():
    exudyn = arm("exudyn")
    coarse = np.abs(arm("mujoco") - exudyn).max()
    fine = np.abs(arm("mujoco", substeps=8) - exudyn).max()
    # the yaw torque spins the arm up to 5 rad/s: joint angles (rad) and hand position (m) agree within
    # 0.01, and again the difference shrinks with MuJoCo's step (measured 0.005, then 0.001)
    assert coarse < 0.01
    assert fine < 0.5 * coarse


def test_cubes_come_to_rest_at_the_same_places():
    bodies = (BodySpec("floor", "plane", ()),
              BodySpec("c1", "box", (0.1, 0.1, 0.1), pos=(0.2, -0.1, 0.3), mass=0.05),
              BodySpec("c2", "box", (0.2, 0.2, 0.15), pos=(-0.3, 0.4, 0.4), mass=0.06),
              BodySpec("table", "box", (0.3, 0.3, 0.3), pos=(0.5, 0.5, 0.15), joint=JointSpec("fixed")),
              BodySpec("c3", "box", (0.08, 0.08, 0.08), pos=(0.52, 0.47, 0.5), mass=0.04),
              BodySpec("c4", "box", (0.1, 0.1, 0.1), pos=(-0.4, -0.4, 0.25), quat=(0.92388, 0, 0, 0.38268), mass=0.1),
              BodySpec("ball", "sphere", (0.05,), pos=(0.0, -0.6, 0.2), mass=0.1))
    rest = {}
    for cls in CORES:
        w = world(cls, *bodies, friction=0.8, restitution=0.2)
        w.tick(1000)
        rest[cls.ENGINE] = {n: (w.get(f"{n}.pos"), w.get(f"{n}.quat"), w.get(f"{n}.linvel")) for n in
                            ("c1", "c2", "c3", "c4", "ball")}
        w.close()
    for name, (pos, quat, vel) in rest["exudyn"].items():
        mj_pos, mj_quat, mj_vel = rest["mujoco"][name]
        # dropped flat, they land flat and stay: MuJoCo's soft contacts sink 0.2 mm, Exudyn's 0.01 mm
        # (g / wn^2); Exudyn's friction jitters during an impact (by up to friction * impact force /
        # mass * step a step) and lets them slip a few mm (measured up to 4 mm) and turn a degree or two
        assert abs(pos[2] - mj_pos[2]) < 5e-4, name
        assert np.linalg.norm(pos[:2] - mj_pos[:2]) < 6e-3, name
        assert 2 * np.arccos(min(1.0, abs(float(quat @ mj_quat)))) < np.radians(3), name
        assert np.linalg.norm(vel) < 5e-3 and np.linalg.norm(mj_vel) < 5e-3, name


@pytest.mark.parametrize("core", ["mujoco", "exudyn"])
def test_two_cubes_runs_on_both_cores_by_one_word(core):
    w = load_scenario(SCENARIOS / "two_cubes.yaml").build(core=core)
    engine = w.core.ENGINE
    assert engine == core
    w.tick(2500)
    aa, bb = w.get("aa.pos"), w.get("bb.pos")
    # what does not depend on the chaotic fall of bb off aa's corner: aa flat on the floor, both at rest
    assert abs(aa[2] - 0.05) < 3e-3 and bb[2] < 0.17
    assert np.linalg.norm(w.get("aa.linvel")) < 0.02 and np.linalg.norm(w.get("bb.linvel")) < 0.02
    w.close()
