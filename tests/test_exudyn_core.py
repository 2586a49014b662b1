"""The Exudyn core on its own: scenes, contact, joints, exact state, edits, queries and refusals, all
with real Exudyn stepping (ports bound by `corekit`). What both cores must do alike is in
test_core_contract.py."""

from __future__ import annotations

import copy
import os

import corekit
import numpy as np
import pytest
from corekit import DT, FLOOR, G, box, run, scene_for_state, trajectory

from dynabrain.modules.exudyn import geometry as geo
from dynabrain.modules.exudyn.core import ExudynCore
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.core import BodySpec, CableSpec, JointSpec, SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, PhysicsDivergedError


def make_core(*bodies: BodySpec, **params):
    return corekit.make_core(ExudynCore, *bodies, **params)


def test_free_fall_is_exact_for_velocity_verlet():
    core, _, out = make_core(BodySpec("ball", "sphere", (0.05,), pos=(0, 0, 10.0), mass=1.0))
    run(core, 250)
    t = 250 * DT * 1e-9
    # velocity Verlet integrates a constant acceleration exactly: z = z0 - g t^2 / 2 to rounding
    assert out["ball.pos"][2] == pytest.approx(10.0 - G * t * t / 2, abs=1e-9)
    assert out["ball.linvel"] == pytest.approx([0, 0, -G * t], abs=1e-9)
    assert np.all(out["ball.angvel"] == 0.0)


def test_two_cubes_come_to_rest_on_the_plane():
    core, _, out = make_core(FLOOR, box("a", (0.1, 0.1, 0.1), (0, 0, 0.3), mass=0.05),
                             box("b", (0.2, 0.2, 0.15), (0.5, 0, 0.4), mass=0.06))
    run(core, 1000)
    sink = G / core.contact_settings()["wn"] ** 2  # static sinking of a body on its contacts
    assert out["a.pos"][2] == pytest.approx(0.05 - sink, abs=5e-4)
    assert out["b.pos"][2] == pytest.approx(0.075 - sink, abs=5e-4)
    assert np.abs(out["body_linvel"]).max() < 1e-3


def bounce_ratios(restitution: float) -> list[float]:
    radius = 0.05
    core, _, out = make_core(FLOOR, BodySpec("ball", "sphere", (radius,), pos=(0, 0, 1.0 + radius), mass=0.1),
                             restitution=restitution)
    z = np.array([f[2] for f in run(core, 900, "ball.pos", out)]) - radius
    apex = [1.0] + [z[i] for i in range(1, len(z) - 1) if z[i - 1] < z[i] >= z[i + 1]]
    return [apex[i + 1] / apex[i] for i in range(2)]


@pytest.mark.parametrize("e", [0.3, 0.8])
def test_restitution_gives_bounce_heights_of_e_squared(e):
    for ratio in bounce_ratios(e):
        assert ratio == pytest.approx(e * e, rel=0.10)


def test_make_freezes_the_others_where_they_stand():
    core, _, out = make_core(FLOOR, box("base", (0.2, 0.2, 0.2), (0, 0, 0.1), mass=0.5),
                             box("top", (0.1, 0.1, 0.1), (0, 0, 0.6), mass=0.1),
                             box("hover", (0.1, 0.1, 0.1), (1, 0, 1.0), mass=0.1))
    run(core, 10)
    hover = out["hover.pos"].copy()
    core.make(["top"])
    assert core.selection == ("top",)
    run(core, 500)
    assert np.array_equal(out["hover.pos"], hover)  # frozen in the air, not falling
    assert np.all(out["hover.linvel"] == 0.0)
    assert out["top.pos"][2] == pytest.approx(0.25, abs=2e-3)  # landed on the frozen base
    core.make(["top", "hover", "base"])  # unfrozen: starts at its frozen pose, at rest
    assert np.array_equal(out["hover.pos"], hover)
    run(core, 100)
    assert out["hover.pos"][2] < hover[2] - 0.1


def relative(out, a, b):
    """Pose of b in a's frame, from the outputs."""
    return geo.compose(geo.inverse((out[f"{a}.pos"], out[f"{a}.quat"])), (out[f"{b}.pos"], out[f"{b}.quat"]))


def test_make_joint_welds_exactly_and_remove_joint_frees():
    core, _, out = make_core(FLOOR, box("a", (0.1, 0.1, 0.1), (0, 0, 0.5), mass=0.1),
                             box("b", (0.1, 0.1, 0.1), (0.12, 0.0, 0.55), quat=(0.92, 0, 0.38, 0), mass=0.1))
    assert core.make_joint("a", "b") == "joint_a_b"
    pos0, quat0 = relative(out, "a", "b")
    for _ in range(300):  # falls, hits the floor, tips over: one rigid body
        core.step(0, DT)
        pos, quat = relative(out, "a", "b")
        assert np.linalg.norm(pos - pos0) < 1e-9
        assert abs(abs(float(np.dot(quat, quat0))) - 1.0) < 1e-12
    assert out["a.pos"][2] < 0.2
    core.remove_joint("joint_a_b")
    with pytest.raises(DynabrainError, match="joint_a_b"):
        core.remove_joint("joint_a_b")


def test_no_collision_keeps_other_contacts_including_sphere_on_sphere():
    scene = (FLOOR, BodySpec("b1", "sphere", (0.05,), pos=(0, 0, 0.05), mass=0.1),
             BodySpec("b2", "sphere", (0.05,), pos=(0, 0, 0.3), mass=0.1),
             BodySpec("b3", "sphere", (0.05,), pos=(0.5, 0, 0.05), mass=0.1),
             BodySpec("b4", "sphere", (0.05,), pos=(0.5, 0, 0.3), mass=0.1))
    core, _, out = make_core(*scene)
    core.no_collision(["b1", "b2"])
    run(core, 300)
    assert out["b2.pos"][2] < 0.06  # fell through b1 (it is pushed aside or lands beside it)
    assert out["b4.pos"][2] > 0.13  # b4 still lands on b3 (or rolls off it, above the floor)


def test_divergence_raises_names_the_joint_and_recovers(tmp_path):
    os.chdir(tmp_path)
    core, inp, out = make_core(*scene_for_state())
    run(core, 5)
    saved = core.get_state()
    reference = trajectory(core, out, 10)
    core.set_state(saved)
    inp["arm.force"][...] = 1e300
    with pytest.raises(PhysicsDivergedError, match="arm"):
        core.step(0, DT)
    inp["arm.force"][...] = 0.0
    core.set_state(saved)  # what the world does after a failed tick: the core recovers exactly
    assert np.array_equal(trajectory(core, out, 10), reference)
    assert not list(tmp_path.iterdir())  # the core writes no files


def test_unknown_names_and_unsupported_features_are_clear_errors(tmp_path):
    core, _, _ = make_core(FLOOR, box("box", (0.1, 0.1, 0.1), (0, 0, 0.05)))
    with pytest.raises(DynabrainError, match="did you mean 'box'"):
        core.make(["boxx"])
    with pytest.raises(DynabrainError, match="did you mean 'floor'"):
        core.body_pose("flor")
    with pytest.raises(DynabrainError, match=r"shape 'cone'.*exudyn"):
        make_core(BodySpec("c", "cone", (0.1,)))
    with pytest.raises(DynabrainError, match=r"joint kind 'ball'.*exudyn"):
        make_core(BodySpec("c", "sphere", (0.1,), joint=JointSpec("ball")))
    with pytest.raises(DynabrainError, match=r"model file.*not supported by the exudyn core"):
        ExudynCore("phys", SceneSpec(model=str(tmp_path / "arm.xml")))
    with pytest.raises(DynabrainError, match=r"floating chain.*exudyn"):
        make_core(box("base", (0.1, 0.1, 0.1), (0, 0, 1)),
                  BodySpec("arm", "capsule", (0.02, 0.3), pos=(0, 0, -0.2), parent="base",
                           joint=JointSpec("hinge", axis=(0, 1, 0))))
    with pytest.raises(DynabrainError, match="integrator"):
        make_core(FLOOR, integrator="leapfrog")


def test_small_hinge_pendulum_period():
    length = 0.5
    core, inp, out = make_core(BodySpec("bob", "sphere", (0.01,), pos=(0, 0, 1.0), mass=1.0,
                                        joint=JointSpec("hinge", axis=(0, 1, 0), anchor=(0, 0, length))))
    inp["bob.force"][...] = 2.0
    run(core, 10)
    inp["bob.force"][...] = 0.0
    q = np.array([float(x) for x in run(core, 2500, "bob.q", out)])
    up = np.flatnonzero((q[:-1] < 0) & (q[1:] >= 0))
    frac = up + (-q[up] / (q[up + 1] - q[up]))
    period = (frac[-1] - frac[0]) / (len(frac) - 1) * DT * 1e-9
    inertia = length**2 + 0.4 * 0.01**2
    assert period == pytest.approx(2 * np.pi * np.sqrt(inertia / (G * length)), rel=2e-3)


def test_joint_range_stops_the_joint():
    core, _, out = make_core(BodySpec("arm", "box", (0.4, 0.04, 0.04), pos=(0.2, 0, 1.0), mass=0.5,
                                      joint=JointSpec("hinge", axis=(0, 1, 0), anchor=(-0.2, 0, 0),
                                                      range=(-0.5, 0.5))))
    q = np.array([float(x) for x in run(core, 1000, "arm.q", out)])
    assert q.max() < 0.55  # gravity swings it to +q; the stop holds it near 0.5 rad
    assert q[-1] == pytest.approx(0.5, abs=0.03)


def test_check_module_passes():
    check_module(ExudynCore("core", SceneSpec(bodies=scene_for_state()))).assert_ok()


def test_cable_hangs_from_the_world_and_stretches_as_ea_says():
    rope = BodySpec("rope", "cable", (0.005,), pos=(0, 0, 2.0), mass=0.2,
                    cable=CableSpec(end=(0, 0, 1.0), segments=8, axial_stiffness=2e3, bending_stiffness=1e-3,
                                    damping=1e-4, attach=("world", "weight")))
    weight = BodySpec("weight", "sphere", (0.05,), pos=(0, 0, 1.0), mass=1.0)
    core, _, out = make_core(rope, weight)
    z = np.array([f[2] for f in run(core, 1000, "weight.pos", out)])
    # the weight bounces on the elastic rope (little damping): its mean over the last second is where it
    # hangs. The rope stretches by its mean tension over EA (weight and half the rope: 1.1 g), each pin by
    # what it holds over its stiffness EA / l (l = 1/8 m): 1.2 g at the top, 1 g at the bottom
    sag = 1.1 * G / 2e3 + (1.2 + 1.0) * G / (2e3 * 8)
    assert z[500:].mean() == pytest.approx(1.0 - sag, abs=1e-3)
    assert np.ptp(z[500:]) > 1e-3  # it still bounces: the mean is the test, not a settled value
    points = core.cable_points("rope")
    assert points.shape == (9, 3) and np.array_equal(points, out["rope.points"])
    assert np.abs(points[:, :2]).max() < 1e-6  # hangs straight down


def test_link_poses_and_velocities_match_exudyns_own_kinematics():
    """The core computes link frames itself (cheaper than asking Exudyn); they must be Exudyn's."""
    import exudyn as exu

    core, inp, out = make_core(
        box("base", (0.2, 0.2, 0.1), (0.1, 0.2, 0.3), quat=(0.9, 0.1, 0.2, 0.3), joint=JointSpec("fixed")),
        box("a", (0.05, 0.05, 0.3), (0.0, 0.1, 0.2), quat=(0.8, 0.3, -0.1, 0.2), parent="base",
            joint=JointSpec("hinge", axis=(0.3, 1, 0.2), anchor=(0, 0, -0.15))),
        BodySpec("b", "capsule", (0.02, 0.2), pos=(0.0, 0.0, 0.3), parent="a",
                 joint=JointSpec("slide", axis=(0, 0.2, 1), anchor=(0.01, 0, 0))),
        BodySpec("c", "sphere", (0.03,), pos=(0.05, 0.0, 0.15), parent="b", joint=JointSpec("hinge", axis=(1, 0, 0))),
        gravity=(0.3, -1.0, -9.81))
    inp["joint_force"][:] = [0.5, 2.0, 0.1]
    run(core, 100)
    s, kind = core._s, exu.OutputVariableType
    tree = s.trees[0]
    for i, (link, marker) in enumerate(zip(tree["links"], tree["markers"], strict=True)):
        p, q, v, w = (f[i] for f in tree["kinematics"].frames(s._x[tree["coords"]], s._v[tree["coords"]]))
        exu_rot = np.array(s.mbs.GetMarkerOutput(marker, kind.RotationMatrix)).reshape(3, 3)
        assert np.allclose(p, s.mbs.GetMarkerOutput(marker, kind.Position), atol=1e-12), link
        assert np.allclose(geo.quat_to_mat(q), exu_rot, atol=1e-12), link
        assert np.allclose(v, s.mbs.GetMarkerOutput(marker, kind.Velocity), atol=1e-12), link
        assert np.allclose(w, s.mbs.GetMarkerOutput(marker, kind.AngularVelocity), atol=1e-12), link
    assert np.allclose(out["c.pos"], geo.compose((p, q), geo.inverse((np.zeros(3), geo.mat_to_quat(
        geo.frame_z((1, 0, 0))))))[0], atol=1e-12)  # the sphere's body frame is its joint frame turned back


def rope_scene():
    return (FLOOR, BodySpec("rope", "cable", (0.005,), pos=(0, 0, 1.5), mass=0.05,
                            cable=CableSpec(end=(0.5, 0, 1.5), segments=4, axial_stiffness=500.0,
                                            attach=("world", "weight"))),
            BodySpec("weight", "sphere", (0.04,), pos=(0.5, 0, 1.5), mass=0.2),
            box("crate", (0.1, 0.1, 0.1), (1.0, 0, 0.05), mass=0.1))


def test_cables_freeze_refuse_welds_and_pass_check_module():
    check_module(ExudynCore("core", SceneSpec(bodies=rope_scene())), ticks=10).assert_ok()
    core, _, out = make_core(*rope_scene())
    run(core, 100)
    saved = core.get_state()
    core.make(["crate", "floor"])  # the rope and its weight freeze where they are
    points, weight = core.cable_points("rope"), out["weight.pos"].copy()
    run(core, 50)
    assert np.array_equal(core.cable_points("rope"), points) and np.array_equal(out["weight.pos"], weight)
    with pytest.raises(DynabrainError, match="cable"):
        core.make_joint("crate", "rope")
    core.make(["crate", "floor", "rope", "weight"])
    run(core, 50)
    assert not np.array_equal(out["weight.pos"], weight)  # moving again
    core.set_state(saved)
    assert core.selection == tuple(core.objects())


def test_prints_nothing_and_writes_no_files(capfd, tmp_path):
    os.chdir(tmp_path)
    core, _, _ = make_core(*rope_scene(), restitution=0.4)  # velocity Verlet and node markers make Exudyn talk
    run(core, 20)
    copy.deepcopy(core)
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == ""
    assert not list(tmp_path.iterdir())


def test_a_push_rides_on_the_carriers_loads_and_comes_off_exactly():
    core, inp, _ = make_core(box("a", (0.1, 0.1, 0.1), (0, 0, 2.0), mass=2.0),
                             box("c", (0.1, 0.1, 0.1), (0.3, 0, 2.0), mass=0.5))
    s = core._s
    gravity, torque = s.free[0][2], s.torque_loads[0]
    assert list(s.mbs.GetLoad(gravity)["loadVector"]) == [0.0, 0.0, -G]
    inp["a.wrench"][:] = (4.0, 0.0, 0.0, 0.0, 0.0, 0.5)
    run(core, 1)
    assert list(s.mbs.GetLoad(gravity)["loadVector"]) == pytest.approx([2.0, 0.0, -G])  # force / mass
    assert list(s.mbs.GetLoad(torque)["loadVector"]) == [0.0, 0.0, 0.5]
    assert list(s.mbs.GetLoad(s.free[1][2])["loadVector"]) == [0.0, 0.0, -G]  # c: untouched
    inp["a.wrench"][:] = 0.0
    run(core, 1)
    assert list(s.mbs.GetLoad(gravity)["loadVector"]) == [0.0, 0.0, -G] and not s.pushing  # gravity, exactly
    assert list(s.mbs.GetLoad(torque)["loadVector"]) == [0.0, 0.0, 0.0]
    core.set_param("gravity", (0.0, 0.0, -3.0))  # a parameter change keeps a push that holds
    inp["c.wrench"][:] = (0.0, 1.0, 0.0, 0.0, 0.0, 0.0)
    run(core, 1)
    core.set_param("gravity", (0.0, 0.0, -1.0))
    assert list(s.mbs.GetLoad(s.free[1][2])["loadVector"]) == pytest.approx([0.0, 2.0, -1.0])
