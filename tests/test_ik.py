"""Inverse kinematics (modules/ik.py, on mink): a target is reached to a fraction of a millimetre and the
servo brings the arm there; several frames at once (whole body) with the other joints held; a target out
of reach is a result with the best pose, not an exception; bad input names the call and the field (an
arm on a post, tests/scenarios/post_arm.yaml). No renderer needed: the humanoid of scenarios/drawer.yaml
reaches the knob where the drawing puts it with whole-body IK, pulls the drawer open and keeps standing."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from dynabrain.modules.ik import IkError, InverseKinematics, Target
from dynabrain.orchestrator import load_world

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
import drawer  # noqa: E402

DOWN = {"axis": [0, 0, 1], "direction": [0, 0, -1]}
ARM = ROOT / "tests" / "scenarios" / "post_arm.yaml"


@pytest.fixture()
def arm():
    world = load_world(ARM)
    world.tick(5)
    yield world
    world.close()


def _tip(world) -> np.ndarray:
    view = world.core.mj
    return np.array(view.data.site_xpos[view.model.site("tip").id])


def test_a_target_is_reached_and_the_servo_takes_the_arm_there(arm):
    ik = InverseKinematics.for_servo(arm, "servo")
    assert ik.joints == ("yaw", "shoulder", "elbow", "wrist")
    target = np.array([0.35, 0.1, 0.45])
    result = ik.solve(Target("tip", pos=target, **DOWN))
    assert result.reached, result.message
    assert result.position_error_m < 1e-5 and result.orientation_error_rad < 1e-4
    assert result.q.shape == (4,) and set(result.pose()) == set(ik.joints)
    assert result.pose()["yaw"] == pytest.approx(np.degrees(np.arctan2(0.1, 0.35)), abs=0.01)
    arm.set("servo.sequence", [result.step("0.6s")])
    arm.tick(500)  # 1 s: the move and a settle
    assert np.linalg.norm(_tip(arm) - target) < 2e-3  # the servo's PD tracking, not the solver, sets this
    pos, quat = ik.frame_pose("tip")
    assert np.allclose(pos, _tip(arm)) and quat.shape == (4,)


def test_a_whole_orientation_is_reached_as_the_axis_that_gives_it(arm):
    ik = InverseKinematics.for_servo(arm)
    down = ik.solve(Target("tip", pos=[0.4, 0.0, 0.45], quat=[0, 0, 1, 0]))  # the hand turned over about y
    assert down.reached and down.orientation_error_rad < 1e-3, down.message
    pointed = ik.solve(Target("tip", pos=[0.4, 0.0, 0.45], **DOWN))
    assert np.allclose(down.q, pointed.q, atol=1e-3)


def test_a_target_out_of_reach_is_a_result_with_the_best_pose(arm):
    ik = InverseKinematics.for_servo(arm)
    far = np.array([1.5, 0.0, 0.4])  # the arm reaches 0.72 m from its shoulder at (0, 0, 0.35)
    result = ik.solve(Target("tip", pos=far))
    assert not result.reached
    assert "out of reach" in result.message and "'tip'" in result.message
    best = np.linalg.norm(far - [0, 0, 0.35]) - 0.72  # stretched straight at it
    assert result.position_error_m == pytest.approx(best, abs=0.01)
    assert result.q.shape == (4,) and np.all(np.isfinite(result.q))
    assert abs(result.pose()["shoulder"]) <= 100 + 1e-6  # joint ranges are kept


def test_several_frames_at_once_and_the_joints_not_chosen_hold(arm):
    """Whole-body style: two frames on one chain, each its target; yaw is left out and stays."""
    ik = InverseKinematics(arm.core, ["shoulder", "elbow", "wrist"])
    elbow_at = np.array([0.15, 0.0, 0.35 + np.sqrt(0.3 ** 2 - 0.15 ** 2)])  # the upper arm 30 degrees forward
    tip_at = elbow_at + np.array([0.3, 0.0, -0.12])  # the forearm level, the fingers down: 0.3 m and 0.12 m
    result = ik.solve([Target("fore", kind="body", pos=elbow_at), Target("tip", pos=tip_at, **DOWN)])
    assert result.reached, result.message
    assert [e.frame for e in result.errors] == ["fore", "tip"]
    out_of_plane = ik.solve(Target("tip", pos=[0.3, 0.2, 0.5]))  # needs yaw, which this solver may not move
    assert not out_of_plane.reached and out_of_plane.position_error_m == pytest.approx(0.2, abs=0.01)


def test_bad_input_names_the_call_and_the_field(arm):
    ik = InverseKinematics.for_servo(arm)
    cases = [
        (lambda: ik.solve(Target("tipp", pos=[0, 0, 1])), "InverseKinematics.solve [targets[0].frame]", "'tip'"),
        (lambda: ik.solve(Target("tip", pos=[0, 1])), "[targets[0].pos]", "3 numbers"),
        (lambda: ik.solve(Target("tip", pos=[0, float("nan"), 1])), "[targets[0].pos]", "finite"),
        (lambda: ik.solve(Target("tip", axis=[0, 0, 0], direction=[0, 0, 1])), "[targets[0].axis]", "length zero"),
        (lambda: ik.solve(Target("tip", axis=[0, 0, 1])), "[targets[0].direction]", "go together"),
        (lambda: ik.solve(Target("tip")), "[targets[0]]", "needs a position"),
        (lambda: ik.solve(Target("tip", pos=[0, 0, 1], kind="joint")), "[targets[0].kind]", "site, body, geom"),
        (lambda: ik.solve([]), "[targets]", "no target"),
        (lambda: ik.solve(Target("tip", pos=[0, 0, 1]), tol_m=0), "[tol_m]", "above 0"),
        (lambda: ik.solve(Target("tip", pos=[0, 0, 1]), start={"elbo": 0.1}), "[start.elbo]", "'elbow'"),
        (lambda: InverseKinematics(arm.core, ["shoulder", "nope"]), "InverseKinematics [joints]", "nope"),
        (lambda: InverseKinematics.for_servo(arm, "servos"), "InverseKinematics.for_servo [servo]", "'servo'"),
        (lambda: InverseKinematics.for_servo(arm, "enc"), "InverseKinematics.for_servo [servo]", "servos: servo"),
        (lambda: ik.solve(Target("tip", quat=[0, 0, 0, 0])), "[targets[0].quat]", "no orientation"),
    ]
    for call, where, what in cases:
        with pytest.raises(IkError) as err:
            call()
        assert where in str(err.value) and what in str(err.value), str(err.value)


def test_the_humanoid_reaches_the_drawn_knob_pulls_the_drawer_open_and_keeps_standing():
    """The drawer brain without eyes: whole-body IK to the knob where the drawing puts it, the grip,
    the pull, letting go; the kid's feet stay planted and the ZMP inside the soles throughout."""
    world = load_world(drawer.SCENARIO)
    try:
        out = drawer.run(world, vision=False)
        knob_now = np.array(world.get("core.knob.pos"))
    finally:
        world.close()
    assert out.reached, [p.message for p in out.poses]
    assert max(p.position_error_m for p in out.poses) < 1e-3
    assert min(p.com_margin_m for p in out.poses) > 0.03  # each planned pose balanced, 3 cm inside the soles
    assert out.gripped and out.grip_gap_m < 3e-3  # the hand's tip on the knob's face (0.4 mm), sag corrected
    assert out.opened_m >= 0.15  # asked 0.18 m
    assert np.allclose(out.knob_true, drawer.KNOB_DRAWN, atol=1e-4)  # where it was when the brain began
    assert knob_now[0] == pytest.approx(drawer.KNOB_DRAWN[0] - out.opened_m, abs=1e-4)
    b = out.balance
    assert not b.left_polygon and b.min_margin_m > 0.01  # the ZMP stayed 1 cm inside the support polygon
    assert b.feet_slip_m < 1e-3 and b.min_pelvis_z_m > 0.27  # feet planted; crouched, never fallen
    assert out.pelvis_z_m == pytest.approx(0.293, abs=0.005)  # standing in its crouch again at the end
