"""A scenario event lets go of a grasp: ``remove_joint`` removes a joint an earlier ``make_joint`` event made
(real MuJoCo: the welded box is carried with the other, then falls when let go), and a joint that no earlier
event made is refused at load with file:line [field]."""

from __future__ import annotations

import numpy as np
import pytest

from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.kernel.errors import DynabrainError

SCENE = """\
name: grasp
world: {step: 2ms, duration: 1s, core: mujoco}
scene:
  - plane: {name: floor}
  - box: {name: hand, size: [0.1, 0.1, 0.1], pos: [0, 0, 0.5], mass: 1}
  - box: {name: cup, size: [0.1, 0.1, 0.1], pos: [0, 0, 0.4], mass: 0.2}
events:
  - {at: 0s, make_joint: [hand, cup]}
  - {at: 0s, set: {core.hand.velocity: [0, 0, 0, 0, 0, 0]}}
  - {at: 0.3s, remove_joint: %s}
"""


def test_a_grasp_made_by_one_event_is_let_go_by_another(tmp_path):
    path = tmp_path / "grasp.yaml"
    path.write_text(SCENE % "joint_hand_cup")
    world = load_world(path)
    try:
        world.tick(140)
        held = np.array(world.get("core.cup.pos"))
        assert abs(held[2] - 0.4) < 0.01  # held up by the hand (the weld sags 5 mm)
        world.tick(200)
        assert world.get("core.cup.pos")[2] < 0.3  # let go at 0.3 s: it fell
    finally:
        world.close()


def test_a_joint_no_event_made_is_refused_at_load(tmp_path):
    path = tmp_path / "grasp.yaml"
    path.write_text(SCENE % "joint_hand_cap")
    with pytest.raises(DynabrainError, match=r"grasp.yaml:10 \[events\[2\]\.remove_joint\].*no joint 'joint_hand_cap'"
                                             r".*did you mean 'joint_hand_cup'"):
        load_world(path)
