"""Whole-body IK (modules/whole_body.py) on the humanoid kid: a hand target is reached with both feet held
and the centre of mass over the soles; chained poses start from the one before; the servo plays the poses
on the real MuJoCo robot and the hand arrives while the ZMP stays inside the support polygon; a target out
of reach is a result, and bad input names the call and the field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynabrain.modules.ik import InverseKinematics, Target
from dynabrain.modules.whole_body import PoseError, WholeBody
from dynabrain.orchestrator import load_world

ROOT = Path(__file__).resolve().parents[1]
STAND = ROOT / "scenarios" / "humanoid_stand.yaml"


@pytest.fixture(scope="module")
def kid():
    world = load_world(STAND)
    world.tick(500)  # into the crouch of the scenario
    yield world
    world.close()


def test_a_hand_target_is_reached_with_the_feet_held_and_the_body_balanced(kid):
    wb = WholeBody.for_servo(kid, "servo")
    feet = {f: wb.frame_pose(f, "body")[0] for f in ("l_foot", "r_foot")}
    low = wb.solve([Target("r_hand_tip", pos=[0.22, -0.05, 0.23])])
    assert low.reached, low.message
    assert low.position_error_m < 1e-3
    assert low.com_margin_m > 0.03
    assert len(low.pose()) == len(low.joints) == 23
    d = kid.core.mj.data
    m = kid.core.mj.model
    twin = type(d)(m)
    twin.qpos[:] = low.q_full
    import mujoco

    mujoco.mj_kinematics(m, twin)
    for foot, where in feet.items():
        assert np.linalg.norm(twin.xpos[m.body(foot).id] - where) < 1e-3
    assert twin.xpos[m.body("pelvis").id][2] < d.xpos[m.body("pelvis").id][2] - 0.003  # it bent to reach low
    assert np.allclose(d.qpos, kid.core.mj.data.qpos)  # the world's own state is untouched


def test_the_servo_plays_chained_poses_and_the_robot_stays_balanced(kid):
    world = kid.fork()
    try:
        wb = WholeBody.for_servo(world, "servo")
        behind = wb.solve([Target("r_hand_tip", pos=[0.2, -0.07, 0.28])])
        across = wb.solve([Target("r_hand_tip", pos=[0.2, 0.03, 0.28])], start=behind)
        assert behind.reached and across.reached, (behind.message, across.message)
        world.set("servo.sequence", [behind.step("0.8s"), across.step("0.6s")])
        margins = []
        for _ in range(40):
            world.tick(50)
            margins.append(float(world.get("zmp.margin")))
        tip, _ = wb.frame_pose("r_hand_tip")
        assert np.linalg.norm(tip - [0.2, 0.03, 0.28]) < 0.01
        assert min(margins) > 0.02
        assert abs(world.get("core.pelvis.pos")[2] - 0.293) < 0.02
    finally:
        world.close()


def test_out_of_reach_is_a_result_and_bad_input_is_named(kid):
    wb = WholeBody.for_servo(kid, "servo")
    far = wb.solve([Target("r_hand_tip", pos=[0.6, 0.0, 0.3])], max_iters=60)
    assert not far.reached and "r_hand_tip" in far.message and "out of reach" in far.message
    with pytest.raises(PoseError, match=r"WholeBody \[feet\[1\]\]: no body 'r_fot'.*r_foot"):
        WholeBody.for_servo(kid, "servo", feet=("l_foot", "r_fot"))
    with pytest.raises(PoseError, match=r"WholeBody.for_servo \[servo\]: no servo module 'servos'"):
        WholeBody.for_servo(kid, "servos")
    with pytest.raises(PoseError, match=r"com_slack_m"):
        WholeBody.for_servo(kid, "servo", com_slack_m=-1)


def test_a_robot_without_a_free_base_is_refused():
    world = load_world(ROOT / "scenarios" / "urdf_arm.yaml")
    try:
        ik = InverseKinematics.for_servo(world, "servo")
        with pytest.raises(PoseError, match="no free joint"):
            WholeBody(world.core, ik.joints, feet=(world.core.mj.model.body(1).name,))
    finally:
        world.close()
