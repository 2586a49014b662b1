"""The World with the real MuJoCo core: failures roll back, forks predict, shipped modules pass
check_module, scene edits name unknown objects."""

from __future__ import annotations

import numpy as np
import pytest

from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.modules.probes import BounceMeter
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.core import COLORS, BodySpec, JointSpec, SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, PhysicsDivergedError
from dynabrain.orchestrator.kernel.world import World


def scene() -> SceneSpec:
    return SceneSpec(bodies=(
        BodySpec("floor", "plane", ()),
        BodySpec("aa", "box", (0.1, 0.1, 0.1), pos=(0.05, 0.05, 0.6), mass=0.05, color=COLORS["blue"]),
        BodySpec("bb", "box", (0.2, 0.2, 0.15), pos=(0.0, 0.0, 0.8), mass=0.06, color=COLORS["yellow"]),
        BodySpec("pole", "capsule", (0.02, 0.4), pos=(1.0, 0.0, 0.5), mass=0.3,
                 joint=JointSpec("hinge", name="pivot", axis=(0.0, 1.0, 0.0), anchor=(0.0, 0.0, 0.2))),
    ))


def world() -> World:
    return World("w", step="2ms", history=100, core=MujocoCore("core", scene()))


def test_divergence_rolls_back_the_tick_and_the_world_goes_on():
    w = world()
    w.tick(10)
    w.set("core.pivot.force", 1e300)
    before = w.snapshot()
    with pytest.raises(PhysicsDivergedError) as err:
        w.tick()
    assert err.value.module == "core" and err.value.tick == 10 and "pivot" in str(err.value)
    assert w.tick_count == 10
    assert w.snapshot().bus.tobytes() == before.bus.tobytes()
    w.set("core.pivot.force", 0.0)
    w.tick(50)
    assert np.isfinite(w.get("aa.pos")).all()
    w.close()


def test_fork_predicts_without_touching_the_world():
    w = world()
    w.tick(20)
    here = w.snapshot()
    plan = w.fork()
    plan.set("core.friction", 0.1)
    plan.make(["aa"])
    plan.tick(300)
    assert plan.get("aa.pos")[2] < 0.06
    assert w.snapshot().bus.tobytes() == here.bus.tobytes() and w.core.selection == tuple(w.core.objects())
    same = w.fork()
    same.tick(100)
    w.tick(100)
    assert same.snapshot().bus.tobytes() == w.snapshot().bus.tobytes()
    for x in (plan, same, w):
        x.close()


def test_scene_edits_name_unknown_objects():
    w = world()
    with pytest.raises(DynabrainError, match=r"make\(\): unknown object 'aaa' \(did you mean 'aa'\?\)"):
        w.make(["aaa"])
    with pytest.raises(DynabrainError, match=r"make_joint\(\): unknown body 'bx'"):
        w.make_joint("aa", "bx")
    with pytest.raises(DynabrainError, match="matches no body"):
        w.no_collision(["zz*"])
    with pytest.raises(DynabrainError, match=r"did you mean 'core\.restitution'"):
        w.set("core.restitutio", 0.5)
    with pytest.raises(DynabrainError, match="is an output"):
        w.set("aa.pos", [0, 0, 1])
    w.close()


def test_make_joint_holds_bodies_together():
    w = world()
    w.tick(100)  # bb has landed on aa's corner
    w.make_joint("aa", "bb")
    rel = w.get("bb.pos") - w.get("aa.pos")
    w.tick(400)
    assert np.allclose(w.get("bb.pos") - w.get("aa.pos"), rel, atol=2e-3)
    w.close()


def test_no_collision_lets_bodies_pass_through():
    w = world()
    w.no_collision(["aa", "bb"])
    w.tick(600)
    assert abs(w.get("bb.pos")[2] - 0.075) < 3e-3  # bb fell through aa onto the floor
    w.close()


def test_check_module_on_the_core_and_the_bounce_meter():
    check_module(MujocoCore("core", scene())).assert_ok()
    meter = BounceMeter("meter", radius=0.05)
    report = check_module(meter, core=MujocoCore("core", scene()))
    report.assert_ok()
    assert "fork" in report.checked


@pytest.mark.parametrize("engine", ["mujoco", "exudyn"])
def test_out_of_range_parameters_are_refused_and_change_nothing(engine):
    from dynabrain.orchestrator.kernel.plugins import resolve_core

    w = World("w", step="2ms", core=resolve_core(engine)("core", scene()))
    w.tick(5)
    for name, value in (("restitution", 1.5), ("friction", -0.1)):
        with pytest.raises(DynabrainError, match=f"{engine} core 'core': parameter {name}"):
            w.set(f"core.{name}", value)
    assert w.get("core.restitution") == 0.0 and w.get("core.friction") == 1.0
    w.close()
