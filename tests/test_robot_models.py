"""Robots users bring (issue 23, item 4): selection on models with tendons, animated robots, a model's
own options.

Models: ``tests/models/tendon_arm.xml`` (written for these tests: an arm with a two-finger hand, a fixed
tendon that closes both fingers and a spatial tendon over a wrapping cylinder, a spare hand without
motors whose fingers a spring tendon holds, and a box), Gymnasium's ``humanoid.xml`` (not written here:
a humanoid with motors and two fixed tendons, hip to knee, shipped with the ``gymnasium`` package this
project depends on) and the kid (``scenarios/models/walk_kick.xml``)."""

from __future__ import annotations

import os
from pathlib import Path

import gymnasium
import mujoco
import numpy as np
import pytest

from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.modules.sensors import Encoders
from dynabrain.orchestrator.kernel.core import SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, ScenarioError
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario.model import load_scenario

HERE = Path(__file__).resolve().parent
ARM = HERE / "models" / "tendon_arm.xml"
KID = HERE.parent / "scenarios" / "models" / "walk_kick.xml"
GYM_HUMANOID = Path(os.path.dirname(gymnasium.__file__)) / "envs" / "mujoco" / "assets" / "humanoid.xml"


def arm_world(**kw) -> World:
    return World("arm", step="2ms", history=100, core=MujocoCore("core", SceneSpec(model=str(ARM)), **kw))


def tendons(w: World) -> set[str]:
    m = w.core.mj.model
    return {m.tendon(i).name for i in range(m.ntendon)}


# -- selection on models with tendons ------------------------------------------------------------------------------
def test_a_model_with_tendons_is_selected_frozen_and_absent():
    w = arm_world()
    w.tick(5)
    w.make(["box"])  # the arm is a robot: animated; the spare hand (no motor) freezes, its spring tendon with it
    assert w.core.selection == ("box",) and tendons(w) == {"grip", "muscle"}
    w.tick(20)
    muscle = w.get("core.sensor.muscle_length").copy()
    w.tick(20)
    assert np.array_equal(w.get("core.sensor.muscle_length"), muscle) and muscle[0] > 0.1  # read, and still
    w.make(["base", "box"], others="absent")  # the spare hand leaves with its tendon
    assert w.core.absent == ("spare_hand",) and tendons(w) == {"grip", "muscle"}
    w.tick(20)
    w.make(["base", "spare_hand", "box"])
    assert tendons(w) == {"grip", "muscle", "spare_spring"} and w.core.absent == ()
    w.tick(20)
    with pytest.raises(DynabrainError, match=r"cannot take object 'base' .*sensor 'shoulder_angle', .* refer to it"):
        w.make(["spare_hand", "box"], others="absent")  # its sensors read it: refused, nothing changed
    assert w.core.selection == ("base", "spare_hand", "box")
    w.close()


def test_a_backtick_across_a_selection_with_tendons_is_bit_exact():
    w = arm_world()
    w.tick(10)
    w.make(["box"])
    w.set("core.joint_target", [0.3, -0.2])
    w.tick(10)
    w.make(["base", "box"], others="absent")
    w.tick(30)
    after = w.snapshot().bus.tobytes()
    w.backtick(35)  # before the absent make: the spare hand frozen again, its tendon still out
    assert w.core.absent == () and w.tick_count == 15 and tendons(w) == {"grip", "muscle"}
    w.tick(5)
    w.make(["base", "box"], others="absent")
    w.tick(30)
    assert w.snapshot().bus.tobytes() == after
    w.close()


def test_gymnasiums_humanoid_with_fixed_tendons_is_animated_or_absent():
    core = MujocoCore("core", SceneSpec(model=str(GYM_HUMANOID)))
    w = World("gym", step="5ms", core=core)
    w.tick(2)
    assert tendons(w) == {"left_hipknee", "right_hipknee"}
    w.make([])  # the humanoid has motors: it is animated, its tendons stay
    w.tick(20)
    assert tendons(w) == {"left_hipknee", "right_hipknee"} and core.selection == ()
    w.make([], others="absent")  # out, with its motors and tendons
    w.tick(20)
    assert tendons(w) == set() and core.mj.model.nu == 0 and core.absent == ("torso",)
    w.close()


COUPLED = """<mujoco>
  <worldbody>
    <body name="a" pos="0 0 1"><joint name="ja" type="hinge"/><geom size=".05"/></body>
    <body name="b" pos="1 0 1"><joint name="jb" type="hinge"/><geom size=".05"/></body>
  </worldbody>
  <tendon><fixed name="couple"><joint joint="ja" coef="1"/><joint joint="jb" coef="-1"/></fixed></tendon>
</mujoco>"""


def test_a_fixed_tendon_between_a_frozen_and_a_simulated_object_is_refused_by_name(tmp_path):
    (tmp_path / "m.xml").write_text(COUPLED)
    w = World("c", step="2ms", core=MujocoCore("core", SceneSpec(model="m.xml"), scenario_dir=str(tmp_path)))
    with pytest.raises(DynabrainError, match=r"tendon 'couple' couples joints of an object that freezes with "
                                             r"joints 'jb' of one that stays simulated; select both"):
        w.make(["b"])
    assert w.core.selection == ("a", "b")
    w.make([])  # both frozen: the tendon goes with them
    assert tendons(w) == set()
    w.tick(5)
    w.close()


# -- animated robots -------------------------------------------------------------------------------------------------
def test_an_animated_arm_follows_its_targets_and_pushes_the_box():
    w = arm_world()
    w.make(["box"])
    box0 = w.get("box.pos").copy()

    def move(shoulder: float, elbow: float, ticks: int) -> None:
        s0, e0 = w.get("core.shoulder.q"), w.get("core.elbow.q")
        for k in range(1, ticks + 1):
            w.set("core.joint_target", [s0 + (shoulder - s0) * k / ticks, e0 + (elbow - e0) * k / ticks])
            w.tick(1)
            assert w.get("core.shoulder.q") == s0 + (shoulder - s0) * k / ticks  # exactly where it is told
        assert w.get("core.shoulder.qd") == pytest.approx((shoulder - s0) / ticks / 0.002)

    move(1.162, 2.262, 250)  # the hand down beside the box ...
    move(1.128, 1.906, 100)
    move(1.31, 1.197, 150)   # ... and along the floor, through where the box stood
    assert np.array_equal(w.get("base.pos"), [0, 0, 0.1])
    w.set("core.joint_target", [np.nan, np.nan])  # NaN: the joints stay where they are
    w.tick(100)
    assert w.get("core.shoulder.q") == 1.31 and w.get("core.shoulder.qd") == 0.0
    assert w.get("box.pos")[0] > box0[0] + 0.1  # pushed away by a body nothing it touches can move
    w.make(["base", "spare_hand", "box"])  # simulated again, with no motor torque: the arm sinks
    w.tick(100)
    assert w.get("core.shoulder.q") > 1.32
    w.close()


def test_an_animated_robot_ignores_its_free_body_inputs_and_cannot_be_placed():
    w = World("kid", step="2ms", core=MujocoCore("core", SceneSpec(model=str(KID))))
    w.make(["ball"])
    pelvis = w.get("pelvis.pos").copy()
    w.set("core.pelvis.velocity", [1.0, 0, 0, 0, 0, 0])
    w.set("core.pelvis.wrench", [0, 0, 500.0, 0, 0, 0])
    w.tick(50)
    assert np.array_equal(w.get("pelvis.pos"), pelvis) and not w.get("pelvis.linvel").any()
    with pytest.raises(DynabrainError, match=r"body 'pelvis' is animated"):
        w.place("pelvis", [1.0, 0, 0.5])
    w.close()


def test_an_animated_robot_keeps_the_joints_made_at_run_time_and_carries_what_is_welded_to_it():
    w = arm_world()
    w.make_joint("palm", "fore", kind="weld")  # within the robot
    w.tick(2)
    w.make(["box"])
    w.make_joint("palm", "box", kind="weld")   # the box held in the hand
    assert w.core.mj.model.neq == 2

    def in_palm() -> np.ndarray:  # the box's position in the palm's frame
        inverse, out = np.empty(4), np.empty(3)
        mujoco.mju_negQuat(inverse, w.get("palm.quat"))
        mujoco.mju_rotVecQuat(out, w.get("box.pos") - w.get("palm.pos"), inverse)
        return out

    palm0, held = w.get("palm.pos").copy(), in_palm()
    for k in range(1, 101):
        w.set("core.shoulder.target", -0.3 * k / 100)
        w.tick(1)
    assert np.linalg.norm(w.get("palm.pos") - palm0) > 0.1 and np.allclose(in_palm(), held, atol=0.01)
    w.close()


ANIMATED = """\
name: animated
world: {{step: 2ms, duration: 0.6s, core: mujoco, history: 50}}
scene: {{model: {model}}}
select: [ball]
modules:
  - {{name: enc, python: dynabrain.modules.sensors:Encoders}}
  - name: servo
    python: dynabrain.modules.servo:Servo
    params:
      sequence:
        - pose: {{l_hip_pitch: -15, r_hip_pitch: -15, l_knee: 30, r_knee: 30, l_elbow: -30, r_elbow: -30}}
          duration: 0.4s
    connect: [[enc.q, servo.q], [enc.qd, servo.qd], [servo.ctrl, core.ctrl], [servo.target, core.joint_target]]
  - {{name: imu, python: dynabrain.modules.sensors:Accelerometer, targets: [imu]}}
  - {{name: lfoot, python: dynabrain.modules.sensors:ForceSensor, targets: [l_foot_ft]}}
  - {{name: zmp, python: dynabrain.modules.zmp:ZmpSensor, targets: [l_foot, r_foot], period: 10ms}}
"""


def test_an_animated_robot_plays_its_servo_program_and_its_sensors_keep_reading(tmp_path):
    (tmp_path / "a.yaml").write_text(ANIMATED.format(model=KID))
    w = load_scenario(tmp_path / "a.yaml").build()
    assert w.core.selection == ("ball",)
    pelvis = w.get("pelvis.pos").copy()
    knee = w.modules["servo"].joints.index("l_knee")
    seen = []
    for _ in range(300):
        w.tick(1)
        seen.append(w.get("enc.q")[knee])
        # the core puts the joint where the servo's target of this tick says: it plays the program exactly
        assert w.get("core.l_knee.q") == w.get("servo.target")[knee]
    assert seen[-1] == pytest.approx(np.radians(30)) and seen[100] < seen[200] < seen[-1]
    assert np.array_equal(w.get("pelvis.pos"), pelvis)  # its root holds where it stood
    assert w.get("imu.acc")[2] == pytest.approx(9.81, abs=0.05)  # held still: the IMU reads g
    assert np.all(np.isfinite(w.get("lfoot.force"))) and np.isfinite(w.get("zmp.inside"))
    bus = w.snapshot().bus.tobytes()
    twin = w.fork()
    w.tick(20)
    w.backtick(20)
    assert w.snapshot().bus.tobytes() == bus
    twin.tick(20)
    w.tick(20)
    assert w.snapshot().bus.tobytes() == twin.snapshot().bus.tobytes()
    twin.close()
    w.close()


def test_encoders_read_an_animated_robot_and_refuse_a_frozen_objects_joint():
    w = arm_world()
    w.make(["box"])  # the arm animated, the spare hand frozen
    w.add_module(Encoders("enc", targets=["shoulder", "elbow"]))
    w.tick(3)
    assert w.get("enc.q").shape == (2,)
    with pytest.raises(DynabrainError, match=r"module 'spare' \[targets\]: joint 'spare_l' belongs to a frozen object"):
        w.add_module(Encoders("spare", targets=["spare_l"]))
    w.make(["base", "box"], others="absent")
    with pytest.raises(DynabrainError, match=r"joint 'spare_l' belongs to a frozen or absent object \(not in the"):
        w.add_module(Encoders("spare", targets=["spare_l"]))
    w.close()


# -- a model's own options -------------------------------------------------------------------------------------------
def opt(w: World) -> tuple[str, str, str, int, float]:
    o = w.core.mj.model.opt
    return (mujoco.mjtIntegrator(o.integrator).name, mujoco.mjtCone(o.cone).name, mujoco.mjtSolver(o.solver).name,
            int(o.iterations), float(o.timestep))


def test_a_model_files_own_options_are_kept_unless_the_scene_overrides_them():
    w = arm_world()  # the file: RK4, pyramidal cones, CG, 30 iterations, 1 ms
    assert opt(w) == ("mjINT_RK4", "mjCONE_PYRAMIDAL", "mjSOL_CG", 30, 0.001) and w.core.params["substeps"] == 2
    w.tick(5)
    w.make(["box"])  # every structure keeps them
    assert opt(w) == ("mjINT_RK4", "mjCONE_PYRAMIDAL", "mjSOL_CG", 30, 0.001)
    w.close()
    w = World("o", step="2ms", core=MujocoCore("core", SceneSpec(model=str(ARM), options={
        "integrator": "implicitfast", "iterations": 12, "timestep": 0.0005})))
    assert opt(w) == ("mjINT_IMPLICITFAST", "mjCONE_PYRAMIDAL", "mjSOL_CG", 12, 0.0005)
    w.close()
    w = arm_world(substeps=1)  # substeps given: they rule the timestep
    assert opt(w)[4] == 0.002
    w.close()
    w = World("kid", step="2ms", core=MujocoCore("core", SceneSpec(model=str(KID))))  # a file that says nothing
    assert opt(w) == ("mjINT_IMPLICITFAST", "mjCONE_ELLIPTIC", "mjSOL_NEWTON", 100, 0.002)
    w.close()


SCENE_OPTIONS = """\
name: options
world: {{step: 2ms, duration: 10ms, core: mujoco}}
scene:
  model: {model}
  options:
    integrater: euler
    solver: cg
    iterations: 1.5
    timestep: 0.5ms
"""


def test_scene_options_override_the_file_and_unknown_ones_are_refused_with_file_line_and_field(tmp_path):
    (tmp_path / "o.yaml").write_text(SCENE_OPTIONS.format(model=ARM))
    with pytest.raises(ScenarioError) as err:
        load_scenario(tmp_path / "o.yaml").build()
    text = str(err.value)
    assert "o.yaml:6 [scene.options.integrater]: MuJoCo has no option 'integrater' (did you mean 'integrator'?)" in text
    assert "o.yaml:8 [scene.options.iterations]: option iterations: a whole number" in text
    assert "2 problems" in text  # the solver and the timestep are good
    (tmp_path / "o.yaml").write_text(SCENE_OPTIONS.format(model=ARM).replace("    integrater: euler\n", "")
                                     .replace("iterations: 1.5", "iterations: 15"))
    w = load_scenario(tmp_path / "o.yaml").build()
    assert opt(w) == ("mjINT_RK4", "mjCONE_PYRAMIDAL", "mjSOL_CG", 15, 0.0005)
    w.tick(5)
    w.close()
