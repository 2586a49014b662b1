"""Bodies a brain can act on: each free body's ``wrench`` (held for the tick) and ``velocity`` (set at
the start of each tick while it holds a value; NaN leaves a component alone) inputs, on both cores, in
worlds: the same physical effect on MuJoCo and Exudyn, what NaN and holding mean, frozen and welded
bodies, rollback and fork bit for bit, scenario events and the MCAP log (replay --verify)."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from dynabrain.modules.exudyn.core import ExudynCore
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.kernel.core import VELOCITY_UNIT, WRENCH_UNIT, BodySpec, SceneSpec
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.scenario.model import load_scenario

CORES = {"mujoco": MujocoCore, "exudyn": ExudynCore}
ENGINES = pytest.mark.parametrize("engine", list(CORES))
NAN = float("nan")
H = 0.002  # the world's step (s)


def world_of(engine: str, *bodies: BodySpec, **params) -> World:
    scene = SceneSpec(bodies=(BodySpec("floor", "plane", ()), *bodies))
    return World("push", step="2ms", seed=1, history=200, core=CORES[engine]("core", scene, **params))


def box(name: str, pos, mass: float = 1.0, size=(0.1, 0.1, 0.1), **kw) -> BodySpec:
    return BodySpec(name, "box", size, pos=pos, mass=mass, **kw)


def floating(engine: str) -> World:
    """A 1 kg box of 10 cm in weightless space (its inertia about each axis: 1/600 kg m^2)."""
    return world_of(engine, box("b", (0.0, 0.0, 1.0)), gravity=(0.0, 0.0, 0.0))


def fingerprint(world: World) -> tuple:
    snap = world.snapshot()
    return snap.tick, snap.bus.tobytes(), repr(snap.states)


# -- the ports ---------------------------------------------------------------------------------------------
def test_both_cores_give_every_free_body_the_same_input_ports():
    bodies = (box("a", (0, 0, 0.3)), box("c", (1, 0, 0.3)),
              BodySpec("post", "box", (0.1, 0.1, 0.5), pos=(2, 0, 0.25), joint=None, parent=None))
    ports = {}
    for engine in CORES:
        world = world_of(engine, *bodies)
        ports[engine] = [(p.name, p.shape, p.unit, p.view_of) for p in world.core.inputs()
                         if "wrench" in p.name or "velocity" in p.name]
        start = world.get("core.body_velocity")
        assert start.shape == (3, 6) and np.isnan(start).all()  # nothing set until a brain writes it
        assert np.array_equal(world.get("core.body_wrench"), np.zeros((3, 6)))
        world.close()
    assert ports["mujoco"] == ports["exudyn"]
    names = [n for n, *_ in ports["mujoco"]]
    assert names == ["body_wrench", "a.wrench", "c.wrench", "post.wrench",
                     "body_velocity", "a.velocity", "c.velocity", "post.velocity"]
    assert {u for _n, _s, u, _v in ports["mujoco"]} == {WRENCH_UNIT, VELOCITY_UNIT}


# -- the same effect on both cores ------------------------------------------------------------------------
@ENGINES
def test_a_push_changes_velocity_by_impulse_over_mass(engine):
    world = floating(engine)
    world.set("core.b.wrench", [1.0, 0.0, 0.0, 0.0, 0.0, 0.01])  # 1 N along x, 0.01 N*m about z
    world.tick(50)  # 0.1 s
    assert world.get("b.linvel") == pytest.approx([0.1, 0.0, 0.0], abs=5e-4)
    assert world.get("b.angvel") == pytest.approx([0.0, 0.0, 0.6], abs=5e-3)  # 0.01 * 0.1 * 600
    world.set("core.b.wrench", [0.0] * 6)
    world.tick(25)  # released: it coasts
    assert world.get("b.linvel") == pytest.approx([0.1, 0.0, 0.0], abs=5e-4)
    world.close()


def test_mujoco_and_exudyn_move_a_pushed_box_alike():
    paths = {}
    for engine in CORES:
        world = floating(engine)
        world.tick(5)
        world.set("core.b.wrench", [2.0, -1.0, 0.5, 0.0, 0.005, 0.0])
        path = []
        for _ in range(50):
            world.tick()
            path.append(world.get("b.pos"))
        world.set("core.b.wrench", [0.0] * 6)
        world.set("core.b.velocity", [NAN, NAN, NAN, 0.0, 0.0, 2.0])
        for _ in range(25):
            world.tick()
            path.append(world.get("b.pos"))
        paths[engine] = (np.array(path), world.get("b.quat"), world.get("b.angvel"))
        world.close()
    (pm, qm, wm), (px, qx, wx) = paths["mujoco"], paths["exudyn"]
    # over 15 cm of travel; Exudyn's velocity Verlet takes a changed force half an engine step late
    assert np.abs(pm - px).max() < 5e-4
    assert abs(float(np.dot(qm, qx))) == pytest.approx(1.0, abs=1e-5)  # the same turn (quaternions up to sign)
    assert wm == pytest.approx([0.0, 0.0, 2.0], abs=1e-6) and wx == pytest.approx([0.0, 0.0, 2.0], abs=1e-6)


@ENGINES
def test_a_velocity_is_set_at_the_start_of_the_tick_and_nan_leaves_a_component_alone(engine):
    world = floating(engine)
    world.set("core.b.velocity", [0.5, -0.2, NAN, NAN, NAN, 1.0])
    world.tick()
    assert world.get("b.linvel") == pytest.approx([0.5, -0.2, 0.0], abs=1e-9)
    assert world.get("b.angvel") == pytest.approx([0.0, 0.0, 1.0], abs=1e-9)
    world.set("core.b.velocity", [NAN, 0.3, NAN, NAN, NAN, NAN])  # x and the turn keep what they have
    world.tick()
    assert world.get("b.linvel") == pytest.approx([0.5, 0.3, 0.0], abs=1e-9)
    assert world.get("b.angvel") == pytest.approx([0.0, 0.0, 1.0], abs=1e-9)
    # in the world frame, whatever the body's orientation: a quarter turn later, x is still x
    world.set("core.b.velocity", [0.0] * 6)
    world.tick()
    world.set("core.b.velocity", [NAN, NAN, NAN, 0.0, 0.0, np.pi / 2 / H])
    world.tick()
    world.set("core.b.velocity", [0.25, 0.0, 0.0, 0.0, 0.0, 0.0])
    world.tick(10)
    turned = np.pi / 2 + 2 * H * 1.0  # a quarter turn in one tick, after two ticks at 1 rad/s
    assert world.get("b.quat") == pytest.approx([np.cos(turned / 2), 0.0, 0.0, np.sin(turned / 2)], abs=1e-9)
    assert world.get("b.linvel") == pytest.approx([0.25, 0.0, 0.0], abs=1e-9)
    world.close()


@ENGINES
def test_a_velocity_stays_set_until_nan_is_written_back(engine):
    world = world_of(engine, box("b", (0.0, 0.0, 1.0)))
    world.set("core.b.velocity", [NAN, NAN, 0.0, NAN, NAN, NAN])  # held at no vertical speed
    world.tick(100)  # 0.2 s: falling, it would have dropped 20 cm
    assert world.get("b.pos")[2] == pytest.approx(1.0, abs=5e-3)
    world.set("core.b.velocity", [NAN] * 6)  # released: it falls
    world.tick(100)
    assert world.get("b.pos")[2] < 0.85 and world.get("b.linvel")[2] < -1.9
    world.close()


@ENGINES
def test_a_pusher_holds_a_block_at_speed_along_the_floor(engine):
    world = world_of(engine, box("block", (0.0, 0.0, 0.05)), friction=0.5)
    world.tick(100)
    x0 = world.get("block.pos")[0]
    world.set("core.block.velocity", [0.3, NAN, NAN, NAN, NAN, NAN])
    world.tick(100)  # 0.2 s at 0.3 m/s, less what friction takes within each tick (mu g h / 2)
    assert world.get("block.pos")[0] - x0 == pytest.approx(0.2 * (0.3 - 0.5 * 9.81 * H / 2), abs=2e-3)
    world.set("core.block.velocity", [NAN] * 6)
    world.tick(100)  # friction stops it within 0.3 / (mu g) = 61 ms
    assert np.linalg.norm(world.get("block.linvel")) < 0.02
    world.close()


# -- frozen and welded bodies -------------------------------------------------------------------------------
@ENGINES
def test_a_frozen_body_ignores_its_inputs(engine):
    world = world_of(engine, box("a", (0, 0, 0.5)), box("c", (1, 0, 0.5)), gravity=(0.0, 0.0, 0.0))
    world.make(["a"])
    world.set("core.c.wrench", [5.0, 0, 0, 0, 0, 0])
    world.set("core.c.velocity", [1.0, 0, 0, 0, 0, 0])
    world.set("core.a.wrench", [1.0, 0, 0, 0, 0, 0])
    world.tick(10)
    assert world.get("c.pos") == pytest.approx([1.0, 0.0, 0.5]) and not world.get("c.linvel").any()
    assert world.get("a.linvel")[0] == pytest.approx(1.0 * 10 * H, abs=5e-4)
    world.close()


@ENGINES
def test_a_welded_body_moves_what_it_is_welded_to(engine):
    world = world_of(engine, box("a", (0, 0, 1.0)), box("c", (0.2, 0, 1.0)), gravity=(0.0, 0.0, 0.0))
    world.make_joint("a", "c")
    world.set("core.c.velocity", [0.0, 0.0, 0.0, 0.0, 0.0, 1.0])  # c's origin still, the pair turning about it
    world.tick(25)  # 0.05 rad
    assert world.get("c.pos") == pytest.approx([0.2, 0.0, 1.0], abs=1e-4)
    assert world.get("a.angvel") == pytest.approx([0.0, 0.0, 1.0], abs=1e-3)
    assert world.get("a.pos") == pytest.approx([0.2 - 0.2 * np.cos(0.05), -0.2 * np.sin(0.05), 1.0], abs=2e-4)
    world.set("core.c.velocity", [0.0] * 6)
    world.tick()
    world.set("core.c.velocity", [NAN] * 6)
    # 1 N on c, 10 cm off the pair's centre: 0.1 N*m on 2/600 + 2 * 0.01 kg m^2 (and 0.5 m/s^2)
    world.set("core.c.wrench", [0.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    world.tick(50)
    assert world.get("a.angvel")[2] == pytest.approx(0.1 / (2 / 600 + 0.02) * 0.1, rel=0.03)
    world.close()


# -- rollback, fork, events, logs ---------------------------------------------------------------------------
@ENGINES
def test_rollback_and_fork_with_inputs_are_bit_identical(engine):
    world = world_of(engine, box("a", (0, 0, 0.05)), box("c", (0.5, 0.0, 0.3), quat=(0.9, 0.3, 0.2, 0.1)))
    world.tick(20)
    start = world.snapshot()
    prints = []
    for k in range(30):
        world.set("core.a.velocity", [0.2 + 0.01 * k, NAN, NAN, NAN, NAN, 0.5 if k % 2 else NAN])
        world.set("core.c.wrench", [0.0, 0.5 * k, 9.81 * 0.5, 0.01, 0.0, 0.0])
        world.tick()
        prints.append(fingerprint(world))
    world.set("core.a.velocity", [NAN] * 6)
    world.tick(5)
    prints += [fingerprint(world)]
    world.backtick(35)  # the inputs come back with the bus (those set at tick 20 too): replay them
    assert world.tick_count == start.tick
    for k in range(30):
        world.set("core.a.velocity", [0.2 + 0.01 * k, NAN, NAN, NAN, NAN, 0.5 if k % 2 else NAN])
        world.set("core.c.wrench", [0.0, 0.5 * k, 9.81 * 0.5, 0.01, 0.0, 0.0])
        world.tick()
        assert fingerprint(world) == prints[k], k
    fork = world.fork()  # the inputs are on the fork's bus: it goes on exactly as the world does
    for w in (world, fork):
        w.set("core.a.velocity", [NAN] * 6)
        w.tick(5)
    assert fingerprint(world)[1:] == fingerprint(fork)[1:] == prints[-1][1:]
    fork.close()
    world.close()


SCENARIO = """\
    name: pushes
    world: {{step: 2ms, duration: 0.6s, core: {engine}}}
    core: {{friction: 0.5}}
    scene:
      - plane: {{name: floor}}
      - box: {{name: block, size: [0.1, 0.1, 0.1], mass: 1, pos: [0, 0, 0.05]}}
      - box: {{name: other, size: [0.1, 0.1, 0.1], mass: 1, pos: [1, 0, 0.05]}}
    events:
      - {{at: 0.1s, set: {{core.block.velocity: [0.3, 0, 0, 0, 0, 0]}}}}
      - {{at: 0.2s, set: {{core.other.wrench: [0, 20, 0, 0, 0, 0]}}}}
      - {{at: 0.4s, set: {{core.other.wrench: [0, 0, 0, 0, 0, 0]}}}}
"""


@ENGINES
def test_scenario_events_set_them_and_the_log_replays_bit_for_bit(engine, tmp_path):
    path = tmp_path / "pushes.yaml"
    path.write_text(textwrap.dedent(SCENARIO.format(engine=engine)))
    sc = load_scenario(path)
    world = sc.build()
    log = tmp_path / "pushes.mcap"
    McapLogger(log).attach(world, sc)
    world.tick(150)
    assert world.get("core.block.velocity") == pytest.approx([0.3, 0, 0, 0, 0, 0])
    assert world.get("block.pos")[0] > 0.05 and world.get("other.linvel")[1] > 0.5
    world.set("core.block.velocity", [NAN] * 6)  # released through the API (recorded as an input edit)
    world.tick(50)
    world.backtick(30)
    world.tick(40)
    world.close()
    result = verify(log)
    assert result.ok, result.divergence
    assert result.last_tick == 210
    again = load_world(path)  # the events alone, in a world of its own
    again.tick(150)
    assert again.get("core.block.velocity") == pytest.approx([0.3, 0, 0, 0, 0, 0])
    again.close()
