"""The servo and the moving floor against physics computed by hand: a PD joint settles like the
second-order system it is, a saturated servo accelerates at tau_max / I, angle-vector programs
interpolate as declared, and the floor tracks its sinusoid after joining a running world."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dynabrain.modules.floor import MovingFloor
from dynabrain.modules.motion import MotionError, parse_motion, parse_pose
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.modules.sensors import Encoders
from dynabrain.modules.servo import Servo
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.core import SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.world import World

MODELS = Path(__file__).resolve().parent.parent / "scenarios" / "models"
ARM = """<mujoco>
  <worldbody>
    <body name="arm">
      <joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="box" size="0.2 0.02 0.02" pos="0.2 0 0" mass="0.5"/>
    </body>
  </worldbody>
</mujoco>"""


@pytest.fixture()
def arm(tmp_path):
    """A one-joint arm with no gravity, no damping, no armature: I = m (l^2/3) about its end."""
    path = tmp_path / "arm.xml"
    path.write_text(ARM)

    def make(**servo_params) -> tuple[World, float]:
        core = MujocoCore("core", SceneSpec(model=str(path)), gravity=[0, 0, 0])
        world = World("arm", step="1ms", history=1000, core=core)
        world.add_module(Encoders("enc", targets=["hinge"]))
        wires = [("enc.q", "servo.q"), ("enc.qd", "servo.qd"), ("servo.hinge.tau", "core.hinge.force")]
        world.add_module(Servo("servo", targets=["hinge"], **servo_params), connect=wires)
        inertia = 0.5 * (0.4**2 + 0.04**2) / 12 + 0.5 * 0.2**2  # box about its centre, moved to the hinge
        return world, inertia

    return make


def test_servo_step_response_is_the_second_order_system(arm):
    kp, zeta = 2.0, 0.5
    world, inertia = arm(kp=kp, kd=0.0, tau_max=100.0)
    wn = math.sqrt(kp / inertia)
    world.set("servo.kd", 2 * zeta * wn * inertia)
    step = 0.5
    world.set("servo.q_ref", [step])
    q = []
    for _ in range(3000):
        world.tick()
        q.append(world.get("enc.q")[0])
    q = np.array(q)
    overshoot = q.max() / step - 1
    assert overshoot == pytest.approx(math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2)), abs=0.01)  # 16.3 %
    outside = np.flatnonzero(np.abs(q - step) > 0.02 * step)
    settling = (outside[-1] + 1) * 1e-3
    predicted = -math.log(0.02 * math.sqrt(1 - zeta**2)) / (zeta * wn)
    assert settling == pytest.approx(predicted, rel=0.15)  # the 2 % envelope bound, crossed at a peak
    world.close()


def test_a_saturated_servo_accelerates_at_its_torque_limit(arm):
    world, inertia = arm(kp=1000.0, kd=0.0, tau_max=0.2)
    world.set("servo.q_ref", [2.0])
    n, dt = 100, 1e-3
    world.tick(n)  # 0.1 s at full torque
    assert world.get("servo.tau")[0] == 0.2
    # semi-implicit Euler under constant acceleration; the encoders read the state at the start of the
    # last tick (they step before the core, as the servo needs them): q after n - 1 steps
    expected = (0.2 / inertia) * dt * dt * (n - 1) * n / 2
    assert world.get("enc.q")[0] == pytest.approx(expected, rel=1e-9)
    world.close()


def test_servo_plays_its_sequence_through_the_target_port(arm):
    world, _ = arm(sequence=[{"pose": [30], "duration": "0.2s"}, [{"hinge": "-0.5rad"}, "0.1s"]],
                   interpolation="linear")
    world.tick(100)  # the target shown is the one the last step used: t = 99 ms
    assert world.get("servo.target")[0] == pytest.approx(math.radians(30 * 0.099 / 0.2), rel=1e-9)
    world.tick(101)
    assert world.get("servo.target")[0] == pytest.approx(math.radians(30), rel=1e-9)
    world.tick(149)
    assert world.get("servo.target")[0] == -0.5  # held after the end
    original = world.get("servo.sequence")
    world.set("servo.sequence", [{"pose": [0], "duration": "1s"}])  # a new program starts from here
    world.tick(501)
    assert world.get("servo.target")[0] == pytest.approx(-0.25, rel=1e-9)
    world.backtick(502)  # before the change: the old program, still holding its last pose
    assert world.get("servo.sequence") == original
    world.tick(10)
    assert world.get("servo.target")[0] == -0.5
    world.close()


def test_motion_programs():
    joints, hinges = ["a", "b"], [False, False]
    start = np.zeros(2)
    m = parse_motion(start, [{"pose": [90, 0], "duration": "1s"}, {"pose": {"b": "1rad"}, "duration": 0.5}],
                     joints, hinges, loop=True)
    assert m.duration_ns == 1_500_000_000
    np.testing.assert_allclose(m.at(0)[0], [0, 0])
    np.testing.assert_allclose(m.at(500_000_000)[0], [math.pi / 4, 0])  # minimum jerk: half way at half time
    pos, rate = m.at(1_000_000_000)
    np.testing.assert_allclose(pos, [math.pi / 2, 0])
    np.testing.assert_allclose(rate, [0, 0], atol=1e-12)  # at rest between steps
    np.testing.assert_allclose(m.at(1_500_000_000)[0], [math.pi / 2, 1.0])  # the mapping kept a
    np.testing.assert_allclose(m.at(2_000_000_000)[0], [math.pi / 2, 0.5])  # looping: last pose -> first
    linear = parse_motion(start, [[[10, 20], "2s"]], joints, hinges, interpolation="linear")
    np.testing.assert_allclose(linear.at(1_000_000_000)[1], np.radians([5, 10]))
    assert parse_pose([1, "25mm"], joints, [False, True], start, "pose")[1] == pytest.approx(0.025)
    with pytest.raises(MotionError, match="3 values for 2 joints"):
        parse_pose([1, 2, 3], joints, hinges, start, "pose")
    with pytest.raises(MotionError, match="did you mean 'b'"):
        parse_motion(start, [{"pose": {"bb": 1}, "duration": "1s"}], joints, hinges)
    with pytest.raises(MotionError, match="positive") as err:
        parse_motion(start, [{"pose": [1, 2], "duration": "0s"}], joints, hinges)
    assert err.value.field == "sequence[0].duration"


def test_servo_drives_the_humanoid_through_its_motors_and_passes_check_module():
    core = MujocoCore("core", SceneSpec(model=str(MODELS / "humanoid.xml")))
    report = check_module(Servo("servo", kp=20.0, sequence=[{"pose": {"l_knee": 30}, "duration": "20ms"}]), core=core)
    report.assert_ok()
    assert {"step -> restore -> step", "fork"} <= set(report.checked)


def floor_world() -> World:
    """The humanoid standing (servo-held) on the earthquake floor, which starts frozen."""
    core = MujocoCore("core", SceneSpec(model=str(MODELS / "earthquake.xml")), friction=1.0)
    world = World("quake", step="2ms", history=200, core=core)
    world.make(["pelvis"])
    world.add_module(Encoders("enc"))
    world.add_module(Servo("servo", pose={"l_knee": 20, "r_knee": 20, "l_hip_pitch": -10, "r_hip_pitch": -10,
                                          "l_ankle_pitch": -10, "r_ankle_pitch": -10}),
                     connect=[("enc.q", "servo.q"), ("enc.qd", "servo.qd"), ("servo.ctrl", "core.ctrl")])
    return world


FLOOR_WIRES = [("core.floor_slide.q", "quake.q"), ("core.floor_slide.qd", "quake.qd"),
               ("core.floor_tilt.q", "quake.tilt_q"), ("core.floor_tilt.qd", "quake.tilt_qd"),
               ("quake.force", "core.floor_slide.force"), ("quake.tilt_torque", "core.floor_tilt.force")]


def test_moving_floor_joins_a_running_world_and_tracks_its_motion():
    world = floor_world()
    world.tick(100)
    floor = MovingFloor("quake", targets=["floor"], amplitude="20mm", frequency="1Hz", tilt_amplitude="3deg",
                        tilt_frequency="0.5Hz", ramp="0.2s", inertia=4.81)
    with pytest.raises(DynabrainError, match=r"module 'quake' \[targets\]: the floor 'floor' is frozen"):
        world.add_module(floor, connect=FLOOR_WIRES)
    assert "quake" not in world.modules  # refused: the world is as it was
    world.make(["pelvis", "floor"])
    world.add_module(MovingFloor("quake", targets=["floor"], amplitude="20mm", frequency="1Hz",
                                 tilt_amplitude="3deg", tilt_frequency="0.5Hz", ramp="0.2s", inertia=4.81),
                     connect=FLOOR_WIRES)
    def reference(k: int, amplitude: float, frequency: float) -> float:
        """The floor's reference k ticks after it joined at t = 0.2 s: a linear 0.2 s ease-in."""
        return min(k * 0.002 / 0.2, 1.0) * amplitude * math.sin(2 * math.pi * frequency * (0.2 + k * 0.002))

    errors = []
    for k in range(1, 751):
        world.tick()
        assert world.get("quake.position") == pytest.approx(reference(k, 0.02, 1.0), abs=1e-12)
        errors.append((abs(world.get("core.floor_slide.q") - reference(k, 0.02, 1.0)),
                       abs(world.get("core.floor_tilt.q") - reference(k, math.radians(3), 0.5))))
    errors = np.array(errors)
    slide_error, tilt_error = errors.max(axis=0)  # the ease-in's corners (velocity steps) cost the most
    assert slide_error < 5e-4 and tilt_error < 2e-3, (slide_error, tilt_error)
    slide_error, tilt_error = errors[150:].max(axis=0)  # once eased in
    assert slide_error < 3e-4 and tilt_error < 1e-3, (slide_error, tilt_error)  # about one step of motion
    assert world.core.body_pose("pelvis")[0][2] > 0.28  # the robot on it stands
    world.close()


def test_moving_floor_switches_off_smoothly_and_passes_check_module():
    world = World("floor", step="2ms")
    world.add_module(MovingFloor("quake", amplitude=0.05, frequency=1.0, ramp=0.1))
    world.tick(100)
    assert abs(world.get("quake.position")) > 0.01
    world.set("quake.enabled", False)
    world.tick(49)
    assert 0 < abs(world.get("quake.position")) < 0.05
    world.tick(1)
    assert world.get("quake.position") == 0.0 and world.get("quake.velocity") == 0.0
    with pytest.raises(DynabrainError, match=r"module 'quake' \[params.ramp\]: must be zero or positive"):
        world.set("quake.ramp", -1)
    world.close()
    check_module(MovingFloor("quake", amplitude=0.05, tilt_amplitude=0.1)).assert_ok()


def test_servo_motor_lag_and_the_fmu_element_names(arm):
    world, _ = arm(kp=1.0, kd=0.0, tau_max=10.0, lag="10ms")
    world.disconnect("servo.q")
    world.connect("enc.hinge.q", "servo.q[1]")  # elements as the FMU adapter names them
    world.set("servo.q_ref[1]", 0.5)
    world.tick()
    assert world.get("servo.tau")[0] == pytest.approx(0.5 * (1 - math.exp(-0.1)), rel=1e-12)
    world.tick()
    first = 0.5 * (1 - math.exp(-0.1))
    command = 1.0 * (0.5 - world.get("enc.q")[0])  # q barely moved: the command is still about 0.5
    assert first < world.get("servo.tau")[0] < first + command * (1 - math.exp(-0.1))
    world.close()
