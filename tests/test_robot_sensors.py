"""Sensors and the ZMP against physics computed by hand: a gyro reads a known spin, an accelerometer
reads g at rest and the centripetal acceleration of a spinning disk, the ankle force sensors carry
the weight above them, the ZMP of a static stance is the projection of the centre of mass; delay and
seeded noise behave as declared, and every sensor passes check_module."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from dynabrain.modules.mujoco.core import STATE, MujocoCore
from dynabrain.modules.sensors import Accelerometer, Encoders, ForceSensor, Gyro
from dynabrain.modules.servo import Servo
from dynabrain.modules.support import convex_hull, feet_support, polygon_margin
from dynabrain.modules.zmp import ZmpSensor
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.core import SceneSpec
from dynabrain.orchestrator.kernel.world import World

MODELS = Path(__file__).resolve().parent.parent / "scenarios" / "models"
STAND = {"l_hip_pitch": -15, "r_hip_pitch": -15, "l_knee": 30, "r_knee": 30, "l_ankle_pitch": -15,
         "r_ankle_pitch": -15, "l_elbow": -30, "r_elbow": -30}
DISK = """<mujoco>
  <worldbody>
    <body name="disk" pos="0 0 0.5">
      <joint name="spin" type="hinge" axis="0 0 1"/>
      <geom type="cylinder" size="0.1 0.01" mass="1"/>
      <site name="rim" pos="0.05 0 0"/>
    </body>
  </worldbody>
  <sensor><gyro name="gyro" site="rim"/><accelerometer name="acc" site="rim"/></sensor>
</mujoco>"""


def humanoid_core() -> MujocoCore:
    return MujocoCore("core", SceneSpec(model=str(MODELS / "humanoid.xml")), friction=1.0)


def standing(pose: dict | None = None, settle: float = 2.0, **extra) -> World:
    """The humanoid holding ``pose`` (degrees) on the ground, settled for ``settle`` seconds."""
    world = World("stand", step="2ms", history=50, core=humanoid_core())
    world.add_module(Encoders("enc"))
    world.add_module(Servo("servo", sequence=[{"pose": pose or STAND, "duration": "0.5s"}]),
                     connect=[("enc.q", "servo.q"), ("enc.qd", "servo.qd"), ("servo.ctrl", "core.ctrl")])
    for module in extra.values():
        world.add_module(module)
    world.tick(round(settle / 0.002))
    return world


@pytest.fixture(scope="module")
def disk_model(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("disk") / "disk.xml"
    path.write_text(DISK)
    return str(path)


def test_gyro_reads_a_known_spin_and_the_accelerometer_its_centripetal_acceleration(disk_model):
    world = World("disk", step="1ms", core=MujocoCore("core", SceneSpec(model=disk_model)))
    world.add_module(Gyro("gyro", targets=["rim"]))
    world.add_module(Accelerometer("acc", targets=["rim"]))
    torque, inertia, radius = 0.01, 0.5 * 1.0 * 0.1**2, 0.05  # I_zz of a solid disk
    world.set("core.spin.force", torque)
    n = 1000
    world.tick(n)
    alpha = torque / inertia
    spin = world.get("gyro.angvel")
    assert spin[2] == pytest.approx(alpha * n * 1e-3, rel=1e-9)  # read after the core's step: omega(t)
    assert abs(spin[0]) < 1e-12 and abs(spin[1]) < 1e-12
    acc = world.get("acc.acc")  # acceleration stage: the state at the start of the last step
    omega = alpha * (n - 1) * 1e-3
    assert acc[0] == pytest.approx(-omega**2 * radius, rel=1e-6)
    assert acc[1] == pytest.approx(alpha * radius, rel=1e-6)
    assert acc[2] == pytest.approx(9.81, rel=1e-9)  # proper acceleration: +g against gravity
    world.close()


def test_ankle_force_sensors_carry_the_weight_above_them_and_the_imu_reads_g():
    world = standing(lf=ForceSensor("lf", targets=["l_foot_ft"]), rf=ForceSensor("rf", targets=["r_foot_ft"]),
                     imu=Accelerometer("imu", targets=["imu"]), gyro=Gyro("gyro", targets=["imu"]),
                     wrist=ForceSensor("wrist", targets=["l_hand_ft"]))
    m = world.core.mj.model
    feet = m.body_mass[m.body("l_foot").id] + m.body_mass[m.body("r_foot").id]
    above = m.body_subtreemass[m.body("pelvis").id] - feet
    weight = above * 9.81
    fz = world.get("lf.force")[2] + world.get("rf.force")[2]
    assert -fz == pytest.approx(weight, rel=0.002)
    assert world.get("lf.force")[2] == pytest.approx(world.get("rf.force")[2], rel=0.02)  # a symmetric stance
    d, hand = world.core.mj.data, m.body("l_hand").id
    weight = np.array([0, 0, -9.81 * m.body_mass[hand]])  # a hanging hand: its weight, and its moment
    lever = d.xipos[hand] - d.site_xpos[m.site("l_hand_ft").id]
    assert np.linalg.norm(world.get("wrist.force")) == pytest.approx(np.linalg.norm(weight), rel=0.01)
    assert np.linalg.norm(world.get("wrist.torque")) == pytest.approx(np.linalg.norm(np.cross(lever, weight)), rel=0.02)
    acc = world.get("imu.acc")  # the pelvis leans a little in the crouch: g, slightly turned
    assert np.linalg.norm(acc) == pytest.approx(9.81, abs=0.005) and acc[2] > 9.8
    assert np.linalg.norm(world.get("gyro.angvel")) < 0.01
    world.close()


@pytest.mark.parametrize("pose", [STAND, {**STAND, "l_shoulder_pitch": -90, "r_shoulder_pitch": -90,
                                          "l_hip_roll": 6, "r_hip_roll": 6, "l_ankle_roll": -6,
                                          "r_ankle_roll": -6, "waist_yaw": 20}])
def test_zmp_of_a_static_stance_is_the_projection_of_the_centre_of_mass(pose):
    world = standing(pose, settle=2.5, zmp=ZmpSensor("zmp", targets=["l_foot", "r_foot"]))
    com = world.core.mj.data.subtree_com[world.core.mj.model.body("pelvis").id]
    zmp = world.get("zmp.zmp")
    assert np.hypot(*(zmp[:2] - com[:2])) < 1e-3, (zmp, com)
    assert world.get("zmp.inside") == 1.0 and world.get("zmp.margin") > 0.01
    forces = world.get("zmp.force")
    assert forces.sum() == pytest.approx(world.core.mj.model.body_subtreemass[1] * 9.81, rel=0.002)
    cops = world.get("zmp.cop")  # each foot's centre of pressure lies under that foot
    assert cops[0][1] > 0.0 > cops[1][1]
    world.close()


def test_zmp_of_a_swaying_robot_equals_the_pressure_centre_of_mujocos_contact_forces():
    """While the robot sways and slips (friction forces matter), each foot's centre of pressure and
    normal force, as the sensor decodes its contact sensor, equal those computed from MuJoCo's contact
    list with mj_contactForce: taken after a full mj_step, both describe the same contacts."""
    world = standing(zmp=ZmpSensor("zmp", targets=["l_foot", "r_foot"]), settle=1.0)
    zmp, core = world.modules["zmp"], world.core
    m, d = core.mj.model, mujoco.MjData(core.mj.model)
    mujoco.mj_setState(m, d, core.get_state()[1], STATE)
    foot_of = {g: k for k, foot in enumerate(("l_foot", "r_foot")) for g in range(m.ngeom)
               if _under(m, int(m.geom_bodyid[g]), m.body(foot).id)}
    d.ctrl[:] = world.get("servo.ctrl")
    wrench, checked = np.zeros(6), 0
    for k in range(300):
        d.xfrc_applied[m.body("pelvis").id] = [12 * np.sin(k * 0.05), 6 * np.cos(k * 0.07), 0, 0, 0, 0]
        mujoco.mj_step(m, d)
        out = feet_support(d.sensordata[zmp._index].tolist(), zmp._nums, 1.0, 0.0)
        force, moment = np.zeros(2), np.zeros((2, 3))
        for i in range(d.ncon):
            c = d.contact[i]
            k_foot = foot_of.get(int(c.geom[0]), foot_of.get(int(c.geom[1])))
            if k_foot is None:
                continue
            mujoco.mj_contactForce(m, d, i, wrench)
            force[k_foot] += wrench[0]
            moment[k_foot] += wrench[0] * c.pos
        for k_foot in range(2):
            assert out[9 + k_foot] == pytest.approx(force[k_foot], rel=1e-9, abs=1e-9)
            if force[k_foot] >= 1.0:
                cop = out[3 + 3 * k_foot:6 + 3 * k_foot]
                assert np.allclose(cop, moment[k_foot] / force[k_foot], rtol=0, atol=1e-12)
                checked += 1
    assert checked > 300  # both feet loaded most of the time
    world.close()


def _under(m: mujoco.MjModel, body: int, ancestor: int) -> bool:
    while body != ancestor and body != 0:
        body = int(m.body_parentid[body])
    return body == ancestor


def test_zmp_follows_a_structure_switch_and_reads_nan_in_the_air():
    world = standing(zmp=ZmpSensor("zmp", targets=["l_foot", "r_foot"]), settle=1.0)
    before = world.core.mj.model
    world.no_collision(["l_hand", "r_hand"])  # an edit: the core recompiles its model, ids may move
    assert world.core.mj.model is not before
    world.tick(5)
    assert world.get("zmp.inside") == 1.0 and world.get("zmp.margin") > 0.03
    world.place("pelvis", [0, 0, 1.0])  # lift the robot: no foot is loaded
    world.tick(2)
    assert np.isnan(world.get("zmp.zmp")).all() and world.get("zmp.inside") == 0.0
    assert (world.get("zmp.force") == 0).all()
    world.close()


def test_support_polygon_geometry():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5], [0.2, 0.9]], dtype=float)
    hull = convex_hull(square)
    assert len(hull) == 4
    assert polygon_margin(np.array([0.5, 0.5]), hull) == pytest.approx(0.5)
    assert polygon_margin(np.array([0.5, 0.1]), hull) == pytest.approx(0.1)
    assert polygon_margin(np.array([1.5, 0.5]), hull) == pytest.approx(-0.5)
    assert polygon_margin(np.array([0.5, 0.0]), convex_hull(np.array([[0, 1], [1, 1.0]]))) == pytest.approx(-1)
    assert polygon_margin(np.array([np.nan, 0]), hull) == float("-inf")


def test_delay_is_whole_periods_of_past_readings_and_noise_is_seeded():
    def run(seed: int) -> tuple[np.ndarray, np.ndarray]:
        world = World("enc", step="2ms", seed=seed, history=20, core=humanoid_core())
        world.add_module(Encoders("now", targets=["l_knee", "r_knee"]))
        world.add_module(Encoders("late", targets=["l_knee", "r_knee"], delay="6ms"))
        world.add_module(Encoders("noisy", targets=["l_knee"], noise=0.01), period="4ms")
        now, late, noisy = [], [], []
        for _ in range(400):
            world.tick()
            now.append(world.get("now.q"))
            late.append(world.get("late.q"))
            noisy.append(world.get("noisy.q")[0] - world.get("now.q")[0])
        world.close()
        return np.array(now), np.array(late), np.array(noisy)

    now, late, noisy = run(0)
    assert np.array_equal(late[3:], now[:-3])  # 6 ms = 3 periods late, exactly
    held = noisy[1::2]  # at 4 ms the noisy encoder samples every other tick
    assert np.std(noisy[0::2]) == pytest.approx(0.01, rel=0.15)
    assert np.all(held != 0)
    again, other = run(0)[2], run(1)[2]
    assert np.array_equal(again, noisy) and not np.array_equal(other, noisy)


def test_noise_switched_on_and_off_while_running_rolls_back_bit_for_bit():
    world = World("enc", step="2ms", seed=3, history=100, core=humanoid_core())
    enc = Encoders("enc", targets=["l_knee"])
    world.add_module(enc)
    world.tick(5)
    assert not enc.steps_change_state()  # no noise, no delay: history keeps one state for the stretch

    def run() -> list[float]:
        readings = []
        for noise in (0.01, 0.0, 0.02):
            world.set("enc.noise", noise)
            for _ in range(10):
                world.tick()
                readings.append(float(world.get("enc.q")[0]))
        return readings

    first = run()
    assert enc.steps_change_state() and len(set(first[20:])) == 10
    world.backtick(30)
    assert run() == first  # the same draws: the generator's state came back with each tick
    world.close()


@pytest.mark.parametrize("make", [
    lambda: ForceSensor("ft", targets=["l_foot_ft"], noise=0.5, torque_noise=0.01, delay="4ms"),
    lambda: Accelerometer("acc", targets=["imu"], noise=0.1),
    lambda: Gyro("gyro", targets=["imu"], delay="2ms"),
    lambda: Encoders("enc", targets=["l_*"], noise=0.001, delay="4ms"),
    lambda: ZmpSensor("zmp", targets=["l_foot", "r_foot"]),
], ids=["force", "accelerometer", "gyro", "encoders", "zmp"])
def test_sensors_pass_check_module(make):
    report = check_module(make(), core=humanoid_core(), ticks=30)
    report.assert_ok()
    assert "step -> restore -> step" in report.checked and "fork" in report.checked


def test_sensors_side_by_side_step_as_one_with_the_same_bits():
    """Sensors next to each other in the schedule (of any kind, due at the same ticks) step as one call
    in the generated tick (`FusedSensors`); a noise level set and cleared, a structure switch (the core
    on another model), a backtick and a fork give the same bits as each sensor stepping on its own."""
    def build(compiled: bool) -> World:
        world = World("fuse", step="2ms", seed=4, history=60, core=humanoid_core(), compiled=compiled)
        world.add_module(Encoders("enc"))
        world.add_module(Servo("servo", sequence=[{"pose": STAND, "duration": "0.3s"}]),
                         connect=[("enc.q", "servo.q"), ("enc.qd", "servo.qd"), ("servo.ctrl", "core.ctrl")])
        for side in "lr":
            world.add_module(ForceSensor(f"{side}_ft", targets=[f"{side}_foot_ft"]))
        world.add_module(Accelerometer("acc", targets=["imu"]))
        world.add_module(Gyro("gyro", targets=["imu"]))
        return world

    fused, plain = build(True), build(False)
    assert "fused_l_ft_gyro(t_ns" in fused.structure.compiled.source

    def both(action) -> None:
        for w in (fused, plain):
            action(w)
        a, b = fused.snapshot(), plain.snapshot()
        assert a.tick == b.tick and a.bus.tobytes() == b.bus.tobytes()

    both(lambda w: w.tick(30))
    both(lambda w: w.set("r_ft.noise", 0.3))
    both(lambda w: w.tick(10))  # r_ft off its fast path: each sensor steps on its own
    both(lambda w: w.set("r_ft.noise", 0.0))
    both(lambda w: w.tick(10))
    both(lambda w: w.no_collision(["l_foot", "r_foot"]))  # another compiled model: ids found again
    both(lambda w: w.tick(10))
    both(lambda w: w.backtick(25))
    both(lambda w: w.tick(12))
    forks = [w.fork() for w in (fused, plain)]
    for f in forks:
        f.tick(7)
    assert forks[0].snapshot().bus.tobytes() == forks[1].snapshot().bus.tobytes()
    assert not np.array_equal(fused.get("acc.acc"), np.zeros(3))
    for w in (fused, plain, *forks):
        w.close()
