"""The bridge offers the body edits (issue 14): a brain adds bodies (a box with units and a colour name, a
mesh of inline vertices), changes a body's material, makes a hinge with an axis and an anchor and
removes a body, over a real Zenoh session on loopback; bad input (an unknown shape, a name in use, a
joint of a body with itself, a bad unit) gets a clear error reply and the world is left as it was."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from dynabrain.bridge.errors import BadRequestError, WorldRefusedError
from dynabrain.bridge.testing import serving
from dynabrain.orchestrator.scenario import load_world

SCENE = """\
name: grow
world: {step: 2ms, core: mujoco}
scene:
  - plane: {name: floor}
  - box: {name: base, size: [0.2, 0.2, 0.1], pos: [0, 0, 0.05], joint: fixed}
"""
CUBE = [list(c) for c in itertools.product((-0.05, 0.05), repeat=3)]


def made(world) -> dict[str, str]:
    """The joints made at run time and their kinds."""
    return {w.name: w.kind for w in world.core._edits.welds}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    path = tmp_path_factory.mktemp("bodies") / "grow.yaml"
    path.write_text(SCENE)
    with serving(load_world(path), "grow") as both:
        yield both


def test_a_brain_adds_bodies_sets_a_material_makes_a_hinge_and_removes_a_body(served):
    server, brain = served
    world = server.world
    brain.tick(5)
    added = brain.add_body("lid", "box", size=["100mm", "100mm", "20mm"], pos=[0, 0, "0.2m"], mass="100g",
                           color="blue", friction=0.3)
    assert added["body"] == "lid" and "core.lid.pos" in added["signals"] and "core.lid.wrench" in added["signals"]
    assert np.allclose(world.core.body_info("lid").geoms[0]["rgba"][:3], [0.15, 0.3, 0.85])
    mesh = brain.add_body("cube", "mesh", mesh={"vertices": CUBE}, scale=[1, 1, 0.5], pos=[0.5, 0, 0.1], mass=0.2)
    assert mesh["body"] == "cube" and world.core.body_info("cube").geoms[0]["type"] == "mesh"
    assert brain.set_material("lid", restitution=0.5) == {"friction": 0.3, "restitution": 0.5, "mass": None}
    assert brain.set_material("lid", friction=None) == {"friction": None, "restitution": 0.5, "mass": None}
    assert brain.set_material("lid", mass=0.2)["mass"] == 0.2  # twice the lid's own 100 g
    assert brain.set_material("lid", mass=None)["mass"] is None  # the model's own again
    assert brain.make_joint("base", "lid", "flap", kind="hinge", axis=[0, 1, 0], anchor=[0.05, 0, "120mm"]) == "flap"
    assert made(world) == {"flap": "hinge"} and world.core.material("lid").restitution == 0.5
    brain.tick(100)
    # the lid turns about the hinge: its anchor stays where it was made
    pos, q = world.get("lid.pos"), world.get("lid.quat")
    assert abs(q[0]) < 0.999, q  # it swung down
    angle = 2 * math.acos(min(1.0, abs(q[0])))
    assert angle > 0.1 and pos[2] < 0.2
    assert brain.remove_body("cube") == {"disconnected": 0}
    assert "cube" not in world.core.bodies()
    brain.backtick(100)  # back across the removal and the hinge: part of history
    assert "cube" in world.core.bodies() and made(world) == {"flap": "hinge"}


def test_bad_body_edits_get_clear_error_replies_and_change_nothing(served):
    server, brain = served
    world = server.world
    brain.tick(1)
    snap = world.snapshot()
    bodies, joints = world.core.bodies(), made(world)
    bad = [(lambda: brain.add_body("blob", "blob", size=[0.1]), WorldRefusedError, "shape 'blob'"),
           (lambda: brain.add_body("base", "sphere", size=[0.1]), WorldRefusedError, "'base' exists already"),
           (lambda: brain.add_body("b", "box", size=["10 parsecs", 1, 1]), WorldRefusedError, "field size"),
           (lambda: brain.add_body("b", "box", size=[0.1] * 3, color="ultraviolet"), WorldRefusedError,
            "field color"),
           (lambda: brain.add_body("b", "box", size=[0.1] * 3, pos=[0, 0, 1e12]), WorldRefusedError, "field pos"),
           (lambda: brain.add_body("m", "mesh", mesh={"vertices": CUBE[:4], "faces": [[0, 1, 9]]}),
            WorldRefusedError, "field mesh"),
           (lambda: brain.add_body("m", "mesh", mesh="/etc/passwd.obj"), BadRequestError, "mesh"),
           (lambda: brain.make_joint("base", "base", kind="hinge"), WorldRefusedError, "body and itself"),
           (lambda: brain.make_joint("base", "floor", kind="screw"), WorldRefusedError, "field kind"),
           (lambda: brain.set_material("base", restitution=2), BadRequestError, "restitution"),
           (lambda: brain.set_material("ghost", friction=0.1), WorldRefusedError, "ghost"),
           (lambda: brain.remove_body("ghost"), WorldRefusedError, "ghost")]
    for call, error, words in bad:
        with pytest.raises(error) as err:
            call()
        assert words in str(err.value), str(err.value)
    assert world.core.bodies() == bodies and made(world) == joints
    now = world.snapshot()
    assert now.tick == snap.tick and now.bus.tobytes() == snap.bus.tobytes() and repr(now.states) == repr(snap.states)
