"""Bad input to the robot modules: each is refused at load with the module, the field and, from a
scenario, the file and line; every problem of a scenario is reported at once."""

from __future__ import annotations

import ctypes.util
import subprocess
import sys
from pathlib import Path

import pytest

from dynabrain.modules.mujoco.access import MujocoLink
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.modules.sensors import Encoders, Gyro
from dynabrain.modules.servo import Servo
from dynabrain.modules.stabilizer import Stabilizer
from dynabrain.modules.zmp import ZmpSensor
from dynabrain.orchestrator.kernel.core import SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, ModuleError, ScenarioError
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario.model import load_scenario

MODELS = Path(__file__).resolve().parent.parent / "scenarios" / "models"
BAD = """name: bad
world: {{step: 2ms, duration: 1s, core: mujoco}}
scene: {{model: {model}}}
modules:
  - {{name: servo, python: dynabrain.modules.servo:Servo, targets: [l_kne, r_knee]}}
  - {{name: short, python: dynabrain.modules.servo:Servo, params: {{pose: [10, 20, 30]}}}}
  - name: program
    python: dynabrain.modules.servo:Servo
    params: {{sequence: [{{pose: {{l_knee: 30}}, duration: 1s}}, {{pose: {{l_kne: 30}}, duration: 1s}}]}}
  - {{name: ft, python: dynabrain.modules.sensors:ForceSensor, targets: [l_foot_f]}}
  - {{name: gyro, python: dynabrain.modules.sensors:Gyro, targets: [l_foot_ft]}}
  - {{name: zmp, python: dynabrain.modules.zmp:ZmpSensor, targets: [l_shin, r_foot]}}
  - {{name: late, python: dynabrain.modules.sensors:Accelerometer, targets: [imu], params: {{delay: 3ms}}}}
  - {{name: stab, python: dynabrain.modules.stabilizer:Stabilizer, params: {{ki: -1}}}}
"""


def problems(tmp_path: Path, text: str) -> list[str]:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as err:
        load_scenario(path).build()
    return [str(p) for p in err.value.problems]


def test_every_bad_module_is_reported_at_load_with_file_line_module_and_field(tmp_path):
    found = problems(tmp_path, BAD.format(model=MODELS / "humanoid.xml"))
    expected = [
        (5, "module 'servo' [targets]: no hinge or slide joint 'l_kne' (did you mean 'l_knee'?)"),
        (6, "module 'short' [params.pose]: an angle-vector of 3 values for 23 joints"),
        (7, "module 'program' [params.sequence[1].pose.l_kne]: no joint 'l_kne' in the servo's joints "
            "(did you mean 'l_knee'?)"),
        (10, "module 'ft' [targets]: no site 'l_foot_f' in the model (did you mean 'l_foot_ft'?)"),
        (11, "module 'gyro' [targets]: site 'l_foot_ft' has no native gyro sensor"),
        (12, "module 'zmp' [targets]: foot 'l_shin' has no contact sensor; the ZMP sensor measures the contact "
             'forces with one: add <contact name="l_shin_contacts" subtree1="l_shin" data="found force pos" '
             "num=\"8\"/> to the model's <sensor>"),
        (13, "module 'late' [params.delay]: delay 0.003 s is not a whole number of the sensor's period"),
        (14, "module 'stab' [params.ki]: must be zero or positive, got -1.0"),
    ]
    assert len(found) == len(expected), "\n".join(found)
    for (line, message), problem in zip(expected, found, strict=True):
        assert f"bad.yaml:{line}" in problem and message in problem, problem


def test_dynabrain_check_lists_them_and_exits_2(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(BAD.format(model=MODELS / "humanoid.xml"))
    done = subprocess.run([sys.executable, "-m", "dynabrain.orchestrator.cli", "check", str(path)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "8 problem(s)" in done.stderr and "bad.yaml:5" in done.stderr and "l_knee" in done.stderr


FOOT = """<mujoco><worldbody><geom name="floor" type="plane" size="1 1 .1"/>
  <body name="foot" pos="0 0 0.012"><freejoint/>
    <geom type="box" size="0.05 0.03 0.01"{collide}/><geom type="sphere" size="0.01" pos="0.06 0 -0.003"{collide}/>
  </body></worldbody>
  <sensor>{sensor}</sensor></mujoco>"""
SOLE = '<contact name="c" subtree1="foot" data="found force pos"/>'


def foot_world(tmp_path: Path, sensor: str, collide: str = "") -> World:
    model = tmp_path / "foot.xml"
    model.write_text(FOOT.format(sensor=sensor, collide=collide))
    return World("w", step="2ms", core=MujocoCore("core", SceneSpec(model=str(model))))


@pytest.mark.parametrize(("sensor", "collide", "message"), [
    (SOLE, ' contype="0" conaffinity="0"', "body 'foot' has no geoms that can collide: a ZMP sensor needs feet"),
    ("", "", "foot 'foot' has no contact sensor; the ZMP sensor measures the contact forces with one: add "
             '<contact name="foot_contacts" subtree1="foot" data="found force pos" num="8"/>'),
    ('<contact name="c" subtree1="foot" data="force pos"/>', "",
     "foot 'foot': its contact sensor 'c' does not report found: give it data=\"found force pos\""),
    ('<contact name="c" body1="foot" data="found force pos" reduce="netforce"/>', "",
     "foot 'foot': its contact sensor 'c' sums the contacts (reduce=\"netforce\"), whose point is not the centre"),
], ids=["no-collision", "no-sensor", "no-found", "netforce"])
def test_zmp_needs_feet_that_touch_and_a_contact_sensor_of_each_contact(tmp_path, sensor, collide, message):
    world = foot_world(tmp_path, sensor, collide)
    with pytest.raises(DynabrainError) as err:
        world.add_module(ZmpSensor("zmp", targets=["foot"]))
    assert f"module 'zmp' [targets]: {message}" in str(err.value)
    with pytest.raises(DynabrainError, match=r"module 'zmp2' \[targets\]: no body 'fot' in the model"):
        world.add_module(ZmpSensor("zmp2", targets=["fot"]))
    with pytest.raises(DynabrainError, match=r"module 'zmp3' \[targets\]: name the feet"):
        world.add_module(ZmpSensor("zmp3"))
    assert list(world.modules) == ["core"]
    world.close()


def test_zmp_refuses_a_step_whose_foot_has_more_contacts_than_its_sensor_holds(tmp_path):
    world = foot_world(tmp_path, '<contact name="c" subtree1="foot" data="found force pos" num="2"/>')
    world.add_module(ZmpSensor("zmp", targets=["foot"]))
    with pytest.raises(ModuleError, match=r"module 'zmp': step\(\) at tick \d+ failed: .*foot 'foot': its contact "
                                          r"sensor 'c' found [3-5] contacts and holds 2 \(num=2\): raise num") as err:
        world.tick(100)  # the foot lands on the box's corners and the sphere
    assert world.tick_count == err.value.tick  # rolled back to the start of the failed tick
    world.close()


def test_modules_refuse_a_world_without_the_mujoco_core():
    with pytest.raises(DynabrainError, match=r"module 'gyro' \[targets\]: needs a physics core, and this world has no"):
        World("w").add_module(Gyro("gyro", targets=["imu"]))

    class OtherCore:
        ENGINE, name = "exudyn", "core"

    with pytest.raises(DynabrainError, match=r"module 'zmp' \[targets\]: needs the mujoco core; this world's core "
                                             r"'core' is 'exudyn'"):
        MujocoLink("zmp", OtherCore())
    with pytest.raises(DynabrainError, match=r"module 'servo' \[targets\]: without a physics core the servo needs"):
        World("w").add_module(Servo("servo"))
    with pytest.raises(DynabrainError, match=r"module 'stab' \[params.kp\]"):
        Stabilizer("stab", kp=-1.0)


def test_a_bad_runtime_sequence_is_refused_and_changes_nothing():
    world = World("w", core=MujocoCore("core", SceneSpec(model=str(MODELS / "humanoid.xml"))))
    world.add_module(Servo("servo"))
    world.tick(3)
    with pytest.raises(DynabrainError, match=r"\[params.sequence\[0\].pose\]: an angle-vector of 2 values"):
        world.set("servo.sequence", [{"pose": [1, 2], "duration": "1s"}])
    assert world.get("servo.sequence") is None
    world.close()


def test_a_camera_where_no_renderer_works_says_so(tmp_path):
    if ctypes.util.find_library("OSMesa") is not None:
        pytest.skip("libOSMesa is installed here, so the OSMesa backend may work: nothing to refuse")
    found = problems(tmp_path, f"""name: cam
world: {{step: 2ms, duration: 1s, core: mujoco}}
scene: {{model: {MODELS / 'humanoid.xml'}}}
modules:
  - {{name: eye, python: dynabrain.modules.camera:Camera, targets: [eye], params: {{backend: osmesa}}}}
  - {{name: blind, python: dynabrain.modules.camera:Camera, targets: [ey]}}
""")
    assert "bad.yaml:5" in found[0] and "bad.yaml:6" in found[1]
    assert "module 'eye' [params.backend]: no offscreen renderer works here (osmesa: " in found[0]
    assert "module 'blind' [targets]: no camera 'ey' in the model (did you mean 'eye'?)" in found[1]


def test_reading_a_robot_left_out_of_the_selection_works_it_is_animated():
    core = MujocoCore("core", SceneSpec(model=str(MODELS / "earthquake.xml")))
    world = World("w", core=core)
    world.make(["floor"])  # the robot is animated, not frozen (issue 23): its joints stay, and are read
    world.add_module(Encoders("enc", targets=["l_knee"]))
    world.tick(2)  # (a frozen object's joints are refused with the reason: tests/test_robot_models.py)
    world.close()
