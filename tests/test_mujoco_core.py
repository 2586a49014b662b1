"""The MuJoCo core with real MuJoCo, driven directly (no World, ports bound by `corekit`). What both
cores must do alike is in test_core_contract.py."""

from __future__ import annotations

import corekit
import mujoco
import numpy as np
import pytest
from corekit import DT, FLOOR, G, box, run, scene_for_state, trajectory

from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator.kernel.core import BodySpec, JointSpec, SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, PhysicsDivergedError
from dynabrain.orchestrator.kernel.world import World


def make_core(*bodies: BodySpec, model: str | None = None, scenario_dir: str | None = None, **params):
    return corekit.make_core(MujocoCore, *bodies, model=model, scenario_dir=scenario_dir, **params)


def test_free_fall_follows_the_integrator():
    core, _, out = make_core(BodySpec("ball", "sphere", (0.05,), pos=(0, 0, 10.0), mass=1.0))
    n = 250
    run(core, n)
    t, h = n * DT * 1e-9, DT * 1e-9
    # semi-implicit Euler: z_n = z0 - g h^2 n (n+1) / 2, i.e. g h t / 2 (4.9 mm here) below z0 - g t^2 / 2
    assert out["ball.pos"][2] == pytest.approx(10.0 - G * h * h * n * (n + 1) / 2, abs=1e-9)
    assert abs(out["ball.pos"][2] - (10.0 - G * t * t / 2)) <= G * h * t / 2 + 1e-9
    assert out["ball.linvel"] == pytest.approx([0, 0, -G * t], abs=1e-9)
    assert out["ball.angvel"] == pytest.approx([0, 0, 0], abs=1e-12)


def test_two_cubes_come_to_rest_on_the_plane():
    core, _, out = make_core(FLOOR, box("a", (0.1, 0.1, 0.1), (0, 0, 0.3), mass=0.05),
                             box("b", (0.2, 0.2, 0.15), (0.5, 0, 0.4), mass=0.06))
    run(core, 1000)
    assert out["a.pos"][2] == pytest.approx(0.05, abs=2e-3)
    assert out["b.pos"][2] == pytest.approx(0.075, abs=2e-3)
    assert np.abs(out["body_linvel"]).max() < 1e-3
    assert out["body_pos"][1] is not None and np.array_equal(out["body_pos"][1], out["a.pos"])


def bounce_ratios(restitution: float) -> list[float]:
    """Apex heights of a sphere's bottom dropped from 1 m, as successive ratios."""
    radius = 0.05
    core, _, out = make_core(FLOOR, BodySpec("ball", "sphere", (radius,), pos=(0, 0, 1.0 + radius), mass=0.1),
                             restitution=restitution, substeps=16)
    z = np.array([f[2] for f in run(core, 900, "ball.pos", out)]) - radius
    apex = [1.0] + [z[i] for i in range(1, len(z) - 1) if z[i - 1] < z[i] >= z[i + 1]]
    return [apex[i + 1] / apex[i] for i in range(2)]


@pytest.mark.parametrize("e", [0.3, 0.8])
def test_restitution_gives_bounce_heights_of_e_squared(e):
    for ratio in bounce_ratios(e):
        assert ratio == pytest.approx(e * e, rel=0.10)


def test_zero_restitution_does_not_bounce():
    core, _, out = make_core(FLOOR, BodySpec("ball", "sphere", (0.05,), pos=(0, 0, 1.05), mass=0.1))
    z = np.array([f[2] for f in run(core, 700, "ball.pos", out)]) - 0.05
    first_contact = int(np.argmax(z < 0))
    assert z[first_contact:].max() < 1e-3
    assert z[-1] == pytest.approx(0.0, abs=1e-3)


def test_make_freezes_the_others_where_they_stand():
    core, _, out = make_core(FLOOR, box("base", (0.2, 0.2, 0.2), (0, 0, 0.1), mass=0.5),
                             box("top", (0.1, 0.1, 0.1), (0, 0, 0.6), mass=0.1),
                             box("hover", (0.1, 0.1, 0.1), (1, 0, 1.0), mass=0.1))
    run(core, 10)
    hover = out["hover.pos"].copy()
    core.make(["top"])
    assert core.selection == ("top",)
    assert core.mj.model.nv == 6  # only the selected box has degrees of freedom
    run(core, 500)
    assert np.array_equal(out["hover.pos"], hover)  # frozen in the air, not falling
    assert np.all(out["hover.linvel"] == 0.0)
    assert out["top.pos"][2] == pytest.approx(0.25, abs=2e-3)  # landed on the frozen base
    pos, _quat = core.body_pose("hover")
    assert np.array_equal(pos, hover)
    core.make(["top", "hover", "base"])  # unfrozen: starts at its frozen pose, at rest
    assert np.array_equal(out["hover.pos"], hover)
    run(core, 100)
    assert out["hover.pos"][2] < hover[2] - 0.1


def test_make_joint_keeps_the_relative_pose():
    core, _, out = make_core(FLOOR, box("a", (0.1, 0.1, 0.1), (0, 0, 0.5), mass=0.1),
                             box("b", (0.1, 0.1, 0.1), (0.12, 0.0, 0.55), quat=(0.92, 0, 0.38, 0), mass=0.1))
    name = core.make_joint("a", "b")
    assert name == "joint_a_b"

    def relative():  # b's pose in a's frame
        neg, pos, quat = np.empty(4), np.empty(3), np.empty(4)
        mujoco.mju_negQuat(neg, out["a.quat"])
        mujoco.mju_rotVecQuat(pos, out["b.pos"] - out["a.pos"], neg)
        mujoco.mju_mulQuat(quat, neg, out["b.quat"])
        return pos, quat

    pos0, quat0 = relative()
    for _ in range(600):  # falls, hits the floor, tips over
        core.step(0, DT)
        pos, quat = relative()
        assert np.linalg.norm(pos - pos0) < 1e-3
        assert 2 * np.arccos(min(1.0, abs(float(np.dot(quat, quat0))))) < 0.02
    assert out["a.pos"][2] < 0.2
    core.remove_joint(name)
    with pytest.raises(DynabrainError, match="joint_a_b"):
        core.remove_joint(name)


def test_divergence_raises_and_names_the_joint(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo's default would append its warnings to MUJOCO_LOG.TXT here
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
    core2, inp2, _ = make_core(*scene_for_state())
    inp2["arm.force"][...] = np.nan
    with pytest.raises(PhysicsDivergedError):
        core2.step(0, DT)
    assert not list(tmp_path.iterdir())  # the core writes no files


def test_unknown_names_and_features_are_clear_errors():
    core, _, _ = make_core(FLOOR, box("box", (0.1, 0.1, 0.1), (0, 0, 0.05)))
    with pytest.raises(DynabrainError, match="did you mean 'box'"):
        core.make(["boxx"])
    with pytest.raises(DynabrainError, match="did you mean 'floor'"):
        core.body_pose("flor")
    with pytest.raises(DynabrainError, match="phys"):
        core.make_joint("box", "nothing")
    with pytest.raises(DynabrainError, match=r"shape 'cone'.*mujoco"):
        make_core(BodySpec("c", "cone", (0.1,)))
    with pytest.raises(DynabrainError, match=r"joint kind 'ball'.*mujoco"):
        make_core(BodySpec("c", "sphere", (0.1,), joint=JointSpec("ball")))


def test_small_hinge_pendulum_period():
    length = 0.5
    core, inp, out = make_core(BodySpec("bob", "sphere", (0.01,), pos=(0, 0, 1.0), mass=1.0,
                                        joint=JointSpec("hinge", axis=(0, 1, 0), anchor=(0, 0, length))))
    inp["bob.force"][...] = 2.0
    run(core, 10)
    inp["bob.force"][...] = 0.0
    q = np.array([float(x) for x in run(core, 2500, "bob.q", out)])
    assert 0.005 < np.abs(q).max() < 0.1
    up = np.flatnonzero((q[:-1] < 0) & (q[1:] >= 0))
    frac = up + (-q[up] / (q[up + 1] - q[up]))
    period = (frac[-1] - frac[0]) / (len(frac) - 1) * DT * 1e-9
    inertia = length**2 + 0.4 * 0.01**2
    assert period == pytest.approx(2 * np.pi * np.sqrt(inertia / (G * length)), rel=2e-3)


MJCF = """
<mujoco>
  <worldbody>
    <geom name="ground" type="plane" size="0 0 1"/>
    <body name="arm" pos="0 0 1">
      <joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="0.2"/>
      <site name="tip" pos="0.3 0 0"/>
    </body>
    <body name="cube" pos="1 0 0.05"><freejoint/><geom type="box" size="0.05 0.05 0.05"/></body>
  </worldbody>
  <actuator><motor name="motor" joint="shoulder" gear="1"/></actuator>
  <sensor>
    <jointpos name="angle" joint="shoulder"/>
    <framepos name="tip" objtype="site" objname="tip"/>
    <accelerometer name="acc" site="tip"/>
  </sensor>
</mujoco>
"""


def test_mjcf_actuators_sensors_and_freezing_them(tmp_path):
    (tmp_path / "arm.xml").write_text(MJCF)
    core, inp, out = make_core(model="arm.xml", scenario_dir=str(tmp_path))
    assert {"motor.ctrl", "shoulder.force"} <= {p.name for p in core.inputs()}
    assert out["sensor.angle"].shape == (1,) and out["sensor.tip"].shape == (3,)
    inp["motor.ctrl"][...] = 0.5
    run(core, 100)
    assert out["sensor.angle"][0] == float(out["shoulder.q"]) != 0.0
    assert np.allclose(out["sensor.tip"], out["sensordata"][1:4])
    saved, angle, sensed = core.get_state(), float(out["shoulder.q"]), out["sensordata"].copy()
    first = np.array(run(core, 20, "sensordata", out))
    core.set_state(saved)
    assert np.array_equal(out["sensordata"], sensed)  # acceleration sensors included
    assert np.array_equal(np.array(run(core, 20, "sensordata", out)), first)
    core.set_state(saved)
    core.make(["cube"])  # the arm freezes: its joint, motor and joint sensor leave the model
    run(core, 50)
    assert float(out["shoulder.q"]) == angle and float(out["shoulder.qd"]) == 0.0
    core.set_state(saved)
    assert float(out["shoulder.q"]) == angle
    with pytest.raises(DynabrainError, match="not found"):
        make_core(model="missing.xml", scenario_dir=str(tmp_path))


def test_hinge_range_is_in_radians():
    core, inp, out = make_core(BodySpec("arm", "capsule", (0.02, 0.4), pos=(0, 0, 1.0), mass=0.5,
                                        joint=JointSpec("hinge", axis=(0, 1, 0), anchor=(0, 0, 0.2),
                                                        range=(-0.5, 0.5))))
    inp["arm.force"][...] = 0.5
    run(core, 500)
    assert 0.45 < float(out["arm.q"]) < 0.52  # held at the 0.5 rad stop (a soft limit)


# -- forks share the compiled model -----------------------------------------------------------------------
def physics_world() -> World:
    return World("share", step="2ms", history=50, core=MujocoCore("core", SceneSpec(bodies=scene_for_state())))


def steps(world: World, n: int) -> list[bytes]:
    out = []
    for _ in range(n):
        world.tick()
        out.append(world.snapshot().bus.tobytes())
    return out


def test_a_fork_and_its_world_share_the_model_and_stay_apart_after_a_parameter_change_in_either():
    world, reference = physics_world(), physics_world()  # the reference never forks: what each must do
    world.tick(30)
    reference.tick(30)
    start = reference.snapshot()
    fork = world.fork()
    assert fork.core.mj.model is world.core.mj.model and fork.core.mj.data is not world.core.mj.data
    fork.set("core.friction", 0.2)  # the fork writes: it copies the model first
    assert fork.core.mj.model is not world.core.mj.model
    assert world.core.mj.model.geom_friction[0, 0] == 1.0 and fork.core.mj.model.geom_friction[0, 0] == 0.2
    other = world.fork()  # shares the world's model again
    assert other.core.mj.model is world.core.mj.model
    world.set("core.gravity", [0.0, 0.0, -3.0])  # now the world writes: the other fork keeps g
    assert other.core.mj.model is not world.core.mj.model
    assert other.core.mj.model.opt.gravity[2] == -9.81 and world.core.mj.model.opt.gravity[2] == -3.0
    assert steps(other, 40) == steps(reference, 40)  # g = -9.81 and friction 1.0, as the other fork
    reference.restore(start)
    reference.set("core.gravity", [0.0, 0.0, -3.0])
    assert steps(world, 40) == steps(reference, 40)
    reference.restore(start)
    reference.set("core.friction", 0.2)
    assert steps(fork, 40) == steps(reference, 40)
    for w in (fork, other, world, reference):
        w.close()


def test_a_closed_forks_data_serves_the_next_fork():
    world = physics_world()
    world.tick(30)
    first = world.fork()
    data = first.core.mj.data
    first.close()
    assert first.core.mj is None  # a closed core keeps nothing
    again = world.fork()
    assert again.core.mj.data is data  # filled with the world's state (mj_copyData), not made anew
    assert steps(again, 30) == steps(world, 30)
    again.close()
    world.close()
