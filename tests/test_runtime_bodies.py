"""The world grows while it runs (issue 14, run-time edits 1-4): bodies added and removed, per-body
friction and restitution, hinge, slider and ball joints, a robot from URDF; on both cores, stepping
for real; each edit part of history (a backtick across it is bit-exact), and bad input refused with
the call and the field named, the world left as it was."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from dynabrain.modules.exudyn.core import ExudynCore
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.kernel.core import COLORS, BodySpec, SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, ScenarioError
from dynabrain.orchestrator.kernel.specs import BodySpecError
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

CORES = {"mujoco": MujocoCore, "exudyn": ExudynCore}
ENGINES = pytest.mark.parametrize("engine", list(CORES))
NAN = float("nan")
ROOT = Path(__file__).resolve().parent.parent


def world_of(engine: str, *bodies: BodySpec, **params) -> World:
    scene = SceneSpec(bodies=(BodySpec("floor", "plane", ()), *bodies))
    return World("grow", step="2ms", history=400, core=CORES[engine]("core", scene, **params))


def box(name: str, pos, mass: float = 1.0, size=(0.1, 0.1, 0.1), **kw) -> BodySpec:
    return BodySpec(name, "box", size, pos=pos, mass=mass, **kw)


def state(world: World) -> tuple:
    """The world's whole state, comparable bit for bit (the bus as bytes: an unset velocity is NaN)."""
    snap = world.snapshot()
    return snap.tick, snap.bus.tobytes(), repr(snap.states), tuple(world.signals)


def distance(world: World, body: str, local, point) -> float:
    """How far the point ``local`` of ``body`` (its frame) is from the world point ``point``."""
    pos, q = world.get(f"{body}.pos"), world.get(f"{body}.quat")
    w, x, y, z = q
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return float(np.linalg.norm(pos + rot @ np.asarray(local) - point))


# -- adding and removing bodies ------------------------------------------------------------------------------
@ENGINES
def test_a_body_added_while_running_falls_and_a_backtick_across_the_add_is_bit_exact(engine):
    world = world_of(engine, box("a", (0, 0, 0.05)))
    world.tick(19)
    before = state(world)  # an edit belongs to the tick it is made at: the add below is part of tick 20
    world.tick(1)
    world.set("core.a.velocity", [0.2, NAN, NAN, NAN, NAN, NAN])  # an input set before the add keeps its value
    name = world.add_body(name="ball", shape="sphere", size=["40mm"], pos=[0.5, 0, "300mm"], mass="50g",
                          color="red")
    assert name == "ball" and world.core.objects() == ["floor", "a", "ball"]
    assert np.array_equal(world.get("ball.pos"), [0.5, 0.0, 0.3])
    assert world.get("core.a.velocity")[0] == 0.2 and np.isnan(world.get("core.ball.velocity")).all()
    assert np.allclose(world.core.body_info("ball").geoms[0]["rgba"], COLORS["red"])
    world.tick(100)
    assert world.get("ball.pos")[2] < 0.3 - 0.5 * 9.81 * 0.15 ** 2  # it falls
    after = state(world)
    world.backtick(100)  # to the tick of the add, after it
    assert "ball" in world.core.bodies()
    world.tick(100)
    assert state(world) == after  # the same future, bit for bit
    world.backtick(101)  # before the add
    assert "ball" not in world.core.bodies() and "core.ball.pos" not in world.signals
    assert state(world) == before
    world.close()


@ENGINES
def test_add_body_from_another_thread_while_the_world_runs(engine):
    world = world_of(engine)
    world.start()
    try:
        time.sleep(0.05)
        world.add_body(BodySpec("box1", "box", ["100mm"] * 3, pos=[0, 0, "500mm"], mass="200g"))
        at = world.tick_count
        while world.tick_count < at + 100:
            time.sleep(0.01)
    finally:
        world.stop()
    assert world.get("box1.pos")[2] < 0.5
    world.close()


@ENGINES
def test_remove_body_takes_its_ports_joints_and_connections_and_a_backtick_brings_it_back(engine):
    world = world_of(engine, box("a", (0, 0, 0.05)), box("b", (0.3, 0, 0.05)))
    world.add_body(box("c", (0.6, 0, 0.05)))
    world.make_joint("a", "c")
    world.no_collision(["a", "c"])
    world.tick(5)
    before = state(world)
    world.tick(1)
    world.remove_body("c")  # added at run time
    world.remove_body("b")  # one of the scene's
    assert world.core.objects() == ["floor", "a"] and world.core.selection == ("floor", "a")
    assert not any(".c." in s or ".b." in s for s in world.signals)
    world.tick(5)
    world.backtick(5)
    assert world.core.objects() == ["floor", "a"]
    world.backtick(1)
    assert state(world) == before
    world.close()


@ENGINES
def test_make_and_no_collision_take_bodies_added_at_run_time(engine):
    world = world_of(engine, box("a", (0, 0, 0.05)))
    world.add_body(box("drop", (0, 0, 0.5), mass=0.2))
    world.make(["a"])  # the new body freezes where it is
    world.tick(50)
    assert np.allclose(world.get("drop.pos"), [0, 0, 0.5])
    world.make(["a", "drop"])
    world.no_collision(["a", "drop"])  # it falls through the box onto the floor
    world.tick(300)
    assert abs(world.get("drop.pos")[2] - 0.05) < 0.01
    world.close()


@ENGINES
def test_a_state_exported_after_add_body_imports_into_a_world_built_without_it(engine):
    world = world_of(engine, box("a", (0, 0, 0.05)))
    world.tick(5)
    world.add_body(box("b", (0.3, 0, 0.3), mass=0.1))
    world.make_joint("a", "b", kind="ball", anchor=[0.15, 0, 0.1])
    world.tick(5)
    other = world_of(engine, box("a", (0, 0, 0.05)))
    other.import_state(world.export_state())
    world.tick(20)
    other.tick(20)
    assert world.get("b.pos").tobytes() == other.get("b.pos").tobytes()
    world.close()
    other.close()


# -- bad input: clear errors, the world left as it was ------------------------------------------------------
@ENGINES
def test_bad_bodies_and_joints_are_refused_naming_call_and_field_and_change_nothing(engine):
    world = world_of(engine, box("a", (0, 0, 0.05)), box("b", (0.3, 0, 0.05)))
    world.tick(3)
    before = state(world)
    refused = [
        (lambda: world.add_body(box("a", (0, 0, 1))), r"add_body: body 'a', field name: a body or joint named 'a'"),
        (lambda: world.add_body(name="c", shape="box", size=[0.1] * 3, color="blu"),
         r"add_body\(\): body 'c', field color: unknown colour 'blu' \(did you mean 'blue'\?\)"),
        (lambda: world.add_body(name="c", shape="box", size=[0.1] * 3, mass="5m"),
         r"field mass: '5m' is a length, expected a mass"),
        (lambda: world.add_body(name="c", shape="box", size=[0.1] * 3, restitution=2),
         r"field restitution: restitution must be from 0 to 1"),
        (lambda: world.add_body(name="c", shape="cone", size=[0.1]), r"shape 'cone' is not supported"),
        (lambda: world.add_body(name="c", shape="box", size=[0.1] * 3, parent="a"), r"field parent: .*top-level"),
        (lambda: world.make_joint("a", "a", kind="hinge"), r"make_joint: a joint between a body and itself \('a'\)"),
        (lambda: world.make_joint("a", "b", kind="screw"), r"make_joint\('a', 'b'\), field kind: unknown joint kind"),
        (lambda: world.make_joint("a", "b", axis=[0, 0, 1]), r"field axis: a weld joint takes no axis"),
        (lambda: world.make_joint("a", "b", kind="hinge", axis=[0, 0, 0]), r"field axis: the axis cannot be zero"),
        (lambda: world.remove_body("nothing"), r"no object 'nothing'"),
        (lambda: world.set("core.a.friction", -1), r"set_material\('a'\), field friction: friction must be from 0"),
    ]
    for call, message in refused:
        with pytest.raises(DynabrainError, match=message):
            call()
        assert state(world) == before
    world.close()


def test_a_kind_the_core_lacks_is_refused_by_name():
    class WeldsOnly(ExudynCore):
        MADE_JOINTS = ("weld",)

    scene = SceneSpec(bodies=(BodySpec("floor", "plane", ()), box("a", (0, 0, 0.05)), box("b", (0.3, 0, 0.05))))
    world = World("w", core=WeldsOnly("core", scene))
    with pytest.raises(DynabrainError, match=r"the exudyn core cannot make a hinge joint \(it makes: weld\)"):
        world.make_joint("a", "b", kind="hinge")
    world.close()


def test_a_body_spec_takes_units_and_colour_names_and_refuses_what_no_core_builds():
    spec = BodySpec("aa", "box", ["100mm"] * 3, mass="50g", pos=[0, 0, "1m"], color="blue", friction=0.4)
    assert spec.size == (0.1, 0.1, 0.1) and spec.mass == 0.05 and spec.pos == (0.0, 0.0, 1.0)
    assert spec.color == COLORS["blue"]
    with pytest.raises(BodySpecError, match=r"body 'aa', field size: sizes must be positive"):
        BodySpec("aa", "box", (0.1, -0.1, 0.1))
    with pytest.raises(BodySpecError, match=r"field color: a colour is a name or \[r, g, b\(, a\)\]"):
        BodySpec("aa", "box", (0.1,) * 3, color=(2, 0, 0))


# -- per-body friction and restitution ------------------------------------------------------------------------
@ENGINES
def test_a_bodys_own_friction_changes_how_far_it_slides_and_a_backtick_undoes_it(engine):
    def slide(friction: float | None) -> float:
        world = world_of(engine, box("a", (0, 0, 0.05)), friction=0.8)
        world.tick(20)  # settle
        if friction is not None:
            world.set("core.a.friction", friction)
            assert world.get("core.a.friction") == friction
        world.set("core.a.velocity", [1.0, NAN, NAN, NAN, NAN, NAN])
        world.tick(1)
        world.set("core.a.velocity", [NAN] * 6)
        world.tick(150)
        x = float(world.get("a.pos")[0])
        world.close()
        return x

    assert slide(0.2) > 2 * slide(None)  # (1 m/s: 6 cm at 0.8, 25 cm at 0.2)
    world = world_of(engine, box("a", (0, 0, 0.05)), friction=0.8)
    world.tick(9)
    before = state(world)
    world.tick(1)
    world.set_material("a", friction=0.2, restitution=0.5)
    assert world.core.material("a").friction == 0.2 and world.get("core.a.restitution") == 0.5
    world.tick(10)
    world.backtick(11)
    assert state(world) == before and world.get("core.a.friction") is None
    world.close()


@ENGINES
def test_a_bodys_own_restitution_makes_it_bounce(engine):
    heights = {}
    for e in (None, 0.8):
        world = world_of(engine, BodySpec("ball", "sphere", (0.05,), pos=(0, 0, 0.55), mass=0.1, restitution=e),
                         restitution=0.0)
        world.tick(170)  # it lands at 0.32 s
        heights[e] = max(world.run(150, record=["ball.pos"])["ball.pos"][:, 2])
        world.close()
    assert heights[None] < 0.06 and heights[0.8] > 0.05 + 0.3 * 0.5


# -- joints made at run time ----------------------------------------------------------------------------------
def hanging(engine: str) -> World:
    """A 50 cm bar beside a fixed post, level, free; gravity will swing whatever joint holds it."""
    world = world_of(engine, BodySpec("post", "box", (0.1, 0.1, 0.1), pos=(0, 0, 1.0), joint="fixed"),
                     box("bar", (0.3, 0, 1.0), size=(0.5, 0.04, 0.04)))
    world.no_collision(["post", "bar"])
    return world


@ENGINES
def test_a_hinge_keeps_its_anchor_and_its_axis(engine):
    world = hanging(engine)
    world.make_joint("post", "bar", kind="hinge", axis=[0, 1, 0], anchor=["50mm", 0, "1m"])
    world.set("core.bar.velocity", [NAN, NAN, NAN, 0, 0, 1.0])  # a push about z, which the hinge refuses
    world.tick(1)
    world.set("core.bar.velocity", [NAN] * 6)
    lows = []
    for _ in range(100):
        world.tick(3)
        assert distance(world, "bar", [-0.25, 0, 0], [0.05, 0, 1.0]) < 2e-3
        assert abs(world.get("bar.pos")[1]) < 2e-3  # it swings in its plane
        lows.append(world.get("bar.pos")[2])
    assert min(lows) < 0.8  # it swings down
    world.close()


@ENGINES
def test_a_ball_joint_keeps_its_anchor_and_lets_the_body_turn_every_way(engine):
    world = hanging(engine)
    world.make_joint("post", "bar", kind="ball", anchor=[0.05, 0, 1.0])
    world.set("core.bar.velocity", [NAN, NAN, NAN, 0, 0, 2.0])  # about z: the ball lets it turn
    world.tick(1)
    world.set("core.bar.velocity", [NAN] * 6)
    for _ in range(50):
        world.tick(3)
        assert distance(world, "bar", [-0.25, 0, 0], [0.05, 0, 1.0]) < 2e-3
    tip = distance(world, "bar", [0.25, 0, 0], [0.05, 0, 1.0]), world.get("bar.pos")
    assert abs(tip[0] - 0.5) < 2e-3 and abs(tip[1][1]) > 0.01  # it has turned out of its plane
    world.close()


@ENGINES
def test_a_slider_keeps_the_orientation_and_the_line(engine):
    world = hanging(engine)
    axis = np.array([1.0, 0.0, -1.0]) / np.sqrt(2)
    world.make_joint("post", "bar", "rail", kind="slider", axis=axis)
    start = world.get("bar.pos")
    for _ in range(50):
        world.tick(4)
        moved = world.get("bar.pos") - start
        assert np.linalg.norm(moved - axis * (moved @ axis)) < 1e-3
        assert np.allclose(world.get("bar.quat"), [1, 0, 0, 0], atol=1e-3)
    travelled = float(moved @ axis)  # slides down its 45 degree rail: g sin 45 t^2 / 2 after 0.4 s
    assert abs(travelled - 0.5 * 9.81 * np.sqrt(0.5) * 0.4 ** 2) < 0.02
    world.close()


@ENGINES
def test_a_joint_made_on_a_body_added_at_run_time_rolls_back_bit_for_bit(engine):
    world = world_of(engine, BodySpec("post", "box", (0.1, 0.1, 0.1), pos=(0, 0, 1.0), joint="fixed"))
    world.tick(4)
    before = state(world)
    world.tick(1)
    world.add_body(box("bar", (0.3, 0, 1.0), size=(0.5, 0.04, 0.04)))
    world.make_joint("post", "bar", kind="hinge", axis=[0, 1, 0], anchor=[0.05, 0, 1.0])
    world.no_collision(["post", "bar"])
    world.tick(40)
    after = state(world)
    world.backtick(40)
    world.tick(40)
    assert state(world) == after
    world.backtick(41)
    assert state(world) == before
    world.close()


# -- scenarios ------------------------------------------------------------------------------------------------
EVENTS = """\
    name: grow
    world: {step: 2ms, duration: 1s, core: CORE}
    scene:
      - plane: {name: floor}
      - box: {name: post, size: [0.1, 0.1, 0.1], pos: [0, 0, 1], joint: fixed}
    events:
      - {at: 0.2s, add_body: {box: {name: bar, size: [0.5, 0.04, 0.04], pos: [0.3, 0, 1], mass: 1kg, color: red}}}
      - {at: 0.2s, no_collision: [post, bar],
         make_joint: {a: post, b: bar, kind: hinge, axis: [0, 1, 0], anchor: [50mm, 0, 1m]}}
      - {at: 0.3s, set: {core.bar.friction: 0.3}}
      - {at: 0.5s, add_body: {sphere: {name: ball, size: [50mm], pos: [1, 0, 0.2], mass: 50g, restitution: 0.9}}}
      - {at: 0.8s, remove_body: ball}
    expect:
      - {at: 1s, that: "abs(norm(bar.pos - [0.05, 0, 1]) - 0.25) < 0.002", name: the hinge holds the bar}
      - {at: 0.7s, that: "ball.z < 0.2", name: the ball falls}
    """


@ENGINES
def test_a_scenario_adds_joins_and_removes_bodies_and_check_accepts_it(engine, tmp_path):
    path = tmp_path / "grow.yaml"
    path.write_text(textwrap.dedent(EVENTS).replace("CORE", engine))
    check = subprocess.run([sys.executable, "-m", "dynabrain.orchestrator.cli.main", "check", str(path)],
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    result = run_scenario(load_scenario(path))
    assert result.ok, result


def test_check_names_every_bad_run_time_edit_with_its_line(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(textwrap.dedent("""\
        name: bad
        world: {step: 2ms, duration: 1s}
        scene:
          - plane: {name: floor}
          - box: {name: post, size: [0.1, 0.1, 0.1], pos: [0, 0, 1], joint: fixed}
          - box: {name: bar, size: [0.1, 0.1, 0.1], pos: [1, 0, 1]}
        events:
          - {at: 0.2s, add_body: {box: {name: post, size: [0.5, 0.04, 0.04]}}}
          - {at: 0.2s, add_body: {box: {name: cube, size: [0.1, 0.1], color: blu}}}
          - {at: 0.3s, make_joint: {a: post, b: post, kind: hinge}}
          - {at: 0.3s, make_joint: {a: post, b: bar, kind: screw}}
          - {at: 0.4s, set: {core.post.restitution: 2}}
          - {at: 0.5s, remove_body: nothing}
        """))
    with pytest.raises(ScenarioError) as err:
        load_world(path)
    found = {(p.line, p.field): p.message for p in err.value.problems}
    assert "a body named 'post' exists at this time" in found[(8, "events[0].add_body.box.name")]
    assert "a box has size of length 3" in found[(9, "events[1].add_body.box.size")]
    assert "unknown colour 'blu'" in found[(9, "events[1].add_body.box.color")]
    assert "a joint between a body and itself ('post')" in found[(10, "events[2].make_joint.b")]
    assert "unknown joint kind 'screw'" in found[(11, "events[3].make_joint.kind")]
    assert "restitution must be at most 1" in found[(12, "events[4].set.core.post.restitution")]
    assert "no object 'nothing' at this time" in found[(13, "events[5].remove_body")]


# -- a robot from a URDF file ---------------------------------------------------------------------------------
def test_the_urdf_arm_scenario_loads_and_passes():
    result = run_scenario(load_scenario(ROOT / "scenarios" / "urdf_arm.yaml"))
    assert result.ok, result


def test_a_urdf_that_does_not_parse_and_a_urdf_on_exudyn_are_refused_naming_the_file(tmp_path):
    (tmp_path / "bad.urdf").write_text('<robot name="x"><link name="a">\n')
    (tmp_path / "s.yaml").write_text("name: s\nworld: {step: 2ms, duration: 1s}\nscene: {model: bad.urdf}\n")
    with pytest.raises(ScenarioError, match=r"s.yaml:3 \[scene.model\]: bad.urdf: .* is not well-formed XML"):
        load_world(tmp_path / "s.yaml")
    (tmp_path / "x.yaml").write_text("name: x\nworld: {step: 2ms, duration: 1s, core: exudyn}\n"
                                     f"scene: {{model: {ROOT / 'scenarios' / 'models' / 'arm.urdf'}}}\n")
    with pytest.raises(ScenarioError, match=r"not supported by the exudyn core.*use core: mujoco for MJCF or URDF"):
        load_world(tmp_path / "x.yaml")
