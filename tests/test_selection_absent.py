"""`make(objects, others="absent")` (issue 18, target 3): the objects not selected leave the simulation.
On both cores a box dropped onto an absent box falls through it to the floor (onto a frozen one it
lands); the absent box's outputs hold where it stood, and selecting it again brings it back there, at
rest. It is part of history (a backtick across it is bit-exact), of forks and exported states, of the
scenario's events and of `replay --verify`. Bad input is refused naming the call and the field, and the
world is left as it was; a model file's body that something refers to is refused by name."""

from __future__ import annotations

import numpy as np
import pytest

from dynabrain.modules.exudyn.core import ExudynCore
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator.kernel.core import BodySpec, SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, ScenarioError
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import read_index
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.scenario.model import load_scenario

CORES = {"mujoco": MujocoCore, "exudyn": ExudynCore}
SCENE = SceneSpec(bodies=(
    BodySpec("floor", "plane"),
    BodySpec("low", "box", (0.2, 0.2, 0.2), pos=(0.0, 0.0, 0.1), mass=1.0),
    BodySpec("drop", "box", (0.1, 0.1, 0.1), pos=(0.0, 0.0, 0.45), mass=0.2),
    BodySpec("far", "sphere", (0.05,), pos=(1.0, 0.0, 0.05), mass=0.1),
))


def world(engine: str, **kw) -> World:
    return World("sel", step="2ms", history=400, core=CORES[engine]("core", SCENE), **kw)


def bus(w: World) -> bytes:
    return w.snapshot().bus.tobytes()


@pytest.mark.parametrize("engine", ["mujoco", "exudyn"])
def test_a_box_falls_through_an_absent_box_and_lands_on_a_frozen_one(engine):
    landed = {}
    for others in ("frozen", "absent"):
        w = world(engine)
        w.tick(5)
        held = w.get("low.pos"), w.get("low.quat")
        w.make(["floor", "drop"], others=others)
        assert w.core.selection == ("floor", "drop")
        assert w.core.absent == (("low", "far") if others == "absent" else ())
        w.tick(300)
        landed[others] = w.get("drop.pos")[2]
        assert np.array_equal(w.get("low.pos"), held[0]) and np.array_equal(w.get("low.quat"), held[1])
        assert not w.get("low.linvel").any() and not w.get("low.angvel").any()
        w.close()
    assert landed["frozen"] == pytest.approx(0.25, abs=0.01)  # on top of the 0.2 m box
    assert landed["absent"] == pytest.approx(0.05, abs=0.01)  # through it, on the floor


@pytest.mark.parametrize("engine", ["mujoco", "exudyn"])
def test_selecting_an_absent_object_again_brings_it_back_where_it_stood_at_rest(engine):
    w = world(engine)
    w.tick(5)
    stood = w.get("far.pos")
    w.make(["floor", "low", "drop"], others="absent")
    w.tick(20)
    assert np.array_equal(w.get("far.pos"), stood)
    w.make(["floor", "low", "drop", "far"])
    assert w.core.absent == () and w.core.selection == tuple(w.core.objects())
    assert np.allclose(w.get("far.pos"), stood, atol=1e-9) and not w.get("far.linvel").any()
    w.tick(20)
    assert np.allclose(w.get("far.pos"), stood, atol=2e-3)  # simulated again: it rests on the floor
    w.close()


@pytest.mark.parametrize("engine", ["mujoco", "exudyn"])
def test_backtick_across_an_absent_make_is_bit_exact_and_forks_and_exports_keep_it(engine):
    w = world(engine)
    w.tick(10)
    w.make(["floor", "drop"], others="absent")
    w.tick(30)
    after = bus(w)
    w.backtick(35)                         # before the make: every object simulated again
    assert w.core.absent == () and w.tick_count == 5
    w.tick(5)
    w.make(["floor", "drop"], others="absent")
    w.tick(30)
    assert bus(w) == after
    fork = w.fork()
    assert fork.core.absent == ("low", "far")
    other = world(engine)
    other.import_state(w.export_state())
    assert other.core.absent == ("low", "far")
    for x in (w, fork, other):
        x.tick(25)
    assert bus(fork) == bus(w) == bus(other)
    for x in (w, fork, other):
        x.close()


def test_bad_input_names_the_call_and_field_and_leaves_the_world_as_it_was():
    w = world("mujoco")
    w.tick(3)
    before, edits = bus(w), w.core._edits
    with pytest.raises(DynabrainError, match=r"make\(\), field others: unknown mode 'absnt' \(did you mean 'absent'"):
        w.make(["drop"], others="absnt")
    with pytest.raises(DynabrainError, match=r"make\(\): unknown object 'drp'"):
        w.make(["drp"], others="absent")
    with pytest.raises(DynabrainError, match=r"field others: unknown mode"):
        w.core.make(["drop"], others="gone")
    w.make_joint("low", "drop", "glue")
    with pytest.raises(DynabrainError, match=r"'absent' would take 'low' .* joint 'glue'"):
        w.make(["floor", "drop"], others="absent")
    w.remove_joint("glue")
    w.make(["floor", "drop"], others="absent")
    with pytest.raises(DynabrainError, match=r"make_joint\('low', 'drop'\): 'low' is out of the simulation"):
        w.make_joint("low", "drop")
    with pytest.raises(DynabrainError, match=r"body 'low' is absent"):
        w.place("low", [0, 0, 1])
    assert w.tick_count == 3
    w.make(["floor", "low", "drop", "far"])
    w.close()
    w = world("mujoco")
    w.tick(3)
    with pytest.raises(DynabrainError):
        w.make(["drop"], others="nope")
    assert bus(w) == before and w.core._edits == edits
    w.close()


MJCF = """<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 .1"/>
    <body name="arm" pos="0 0 .5"><joint name="hinge" type="hinge"/><geom size=".05"/>
      <body name="hand" pos=".1 0 0"><geom size=".03"/><site name="tip"/></body></body>
    <body name="free_box" pos="1 0 .2"><freejoint/><geom type="box" size=".05 .05 .05"/></body>
    <body name="watched" pos="-1 0 .2"><freejoint/><geom type="box" size=".05 .05 .05"/></body>
  </worldbody>
  <sensor><framepos name="where" objtype="body" objname="watched"/></sensor>
</mujoco>"""


def test_a_model_file_deletes_unreferenced_objects_and_refuses_referenced_ones(tmp_path):
    (tmp_path / "m.xml").write_text(MJCF)
    core = MujocoCore("core", SceneSpec(model="m.xml"), scenario_dir=str(tmp_path))
    w = World("mjcf", step="2ms", core=core)
    w.tick(2)
    ngeom = core.mj.model.ngeom
    w.make(["arm", "watched"], others="absent")
    assert core.absent == ("free_box",) and core.mj.model.ngeom == ngeom - 1
    w.tick(2)
    with pytest.raises(DynabrainError, match=r"cannot take object 'watched' .* sensor 'where' refers to it"):
        w.make(["arm"], others="absent")
    assert core.absent == ("free_box",)
    w.make(["arm", "watched", "free_box"])
    assert core.mj.model.ngeom == ngeom and core.selection == tuple(core.objects())
    w.close()


SCENARIO = """\
name: absent
world: {{step: 2ms, core: {engine}, duration: 0.2s}}
scene:
  - plane: {{name: floor}}
  - box: {{name: low, size: [0.2, 0.2, 0.2], pos: [0, 0, 0.1], mass: 1}}
  - box: {{name: drop, size: [0.1, 0.1, 0.1], pos: [0, 0, 0.45], mass: 0.2}}
events:
  - {{at: 10ms, make: {{objects: [floor, drop], others: {others}}}}}
  - {{at: 150ms, make: [floor, drop, low]}}
"""


@pytest.mark.parametrize("engine", ["mujoco", "exudyn"])
def test_a_scenario_event_makes_others_absent_and_verify_replays_it(tmp_path, engine, monkeypatch):
    (tmp_path / "s.yaml").write_text(SCENARIO.format(engine=engine, others="absent"))
    sc = load_scenario(tmp_path / "s.yaml")
    w = sc.build()
    w.tick(50)
    assert w.core.absent == ("low",)
    w.tick(30)
    assert w.core.absent == ()
    w.close()
    (tmp_path / "s.yaml").write_text(SCENARIO.format(engine=engine, others="absent").partition("events:")[0])
    sc = load_scenario(tmp_path / "s.yaml")
    w = sc.build()
    path = tmp_path / "api.mcap"
    McapLogger(path, window=8, batch=4).attach(w, sc)
    w.tick(3)
    w.make(["floor", "drop"], others="absent")
    w.tick(150)                            # the drop falls through where the low box stood
    assert w.get("drop.pos")[2] < 0.2
    w.backtick(5)
    w.make(["floor", "drop", "low"])
    w.tick(10)
    w.close()
    made = [e["detail"] for e in read_index(path).events if e["kind"] == "make" and e.get("source") == "api"]
    assert made[0]["others"] == "absent" and made[-1]["others"] == "frozen"
    result = verify(path)
    assert result.ok, result.divergence
    if engine == "mujoco":  # the check has teeth: the same log, its others frozen, diverges
        import dynabrain.orchestrator.logs.verify as v

        real = v.apply_edit

        def frozen(world, kind, d, base_dir="."):
            return real(world, kind, {**d, "others": "frozen"} if kind == "make" else d, base_dir)

        monkeypatch.setattr(v, "apply_edit", frozen)
        assert not verify(path).ok


def test_a_scenario_with_a_bad_make_is_refused_naming_the_field(tmp_path):
    (tmp_path / "s.yaml").write_text(SCENARIO.format(engine="mujoco", others="gone"))
    with pytest.raises(ScenarioError, match=r"others.*unknown mode 'gone'"):
        load_scenario(tmp_path / "s.yaml").build()


@pytest.mark.parametrize("engine", ["mujoco", "exudyn"])
def test_bodies_added_at_run_time_can_be_absent_and_removed_while_absent(engine):
    w = world(engine)
    w.tick(2)
    w.add_body(name="extra", shape="box", size=[0.1] * 3, pos=[0, 0, 0.3], mass=0.1)
    w.make(["floor", "drop"], others="absent")
    assert w.core.absent == ("low", "far", "extra")
    w.tick(100)
    assert w.get("drop.pos")[2] < 0.3  # through both the low box and the extra one
    assert np.array_equal(w.get("extra.pos"), [0, 0, 0.3])
    w.remove_body("extra")
    assert w.core.absent == ("low", "far")
    w.tick(2)
    w.close()
