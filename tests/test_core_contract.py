"""What every physics core must do the same way, checked on MuJoCo and Exudyn alike with real stepping:
save and restore bit for bit, across structural edits and parameter changes, collision filters, scene
queries, fork and place. Each engine's own behaviour (contact models, tolerances, files) is in its own
test file."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from corekit import FLOOR, G, bind, box, make_core, run, scene_for_state, trajectory

from dynabrain.modules.exudyn.core import ExudynCore
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator.kernel.core import JointSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError

ENGINES = pytest.mark.parametrize("engine", [MujocoCore, ExudynCore], ids=["mujoco", "exudyn"])


@ENGINES
def test_save_restore_is_bit_exact(engine):
    core, inp, out = make_core(engine, *scene_for_state())
    inp["joint_force"][:] = 0.3
    run(core, 100)
    saved = core.get_state()
    first = trajectory(core, out, 50)
    core.set_state(saved)
    assert np.array_equal(trajectory(core, out, 50), first)
    before = copy.deepcopy(saved[1])
    core.set_state(saved)
    assert np.array_equal(saved[1], before)  # set_state does not keep or mutate the saved value


def edited_run(core, inp, out):
    """Steps interleaved with every kind of structural edit, a parameter change and the free bodies'
    inputs (a wrench, a velocity set, part NaN, then released)."""
    parts = [trajectory(core, out, 20)]
    core.make(["a", "arm"])
    inp["a.wrench"][:] = (0.0, 0.2, 0.6, 0.0, 0.001, 0.0)
    parts.append(trajectory(core, out, 20))
    core.set_param("friction", 0.4)
    core.make_joint("a", "c")
    inp["a.velocity"][:] = (0.3, np.nan, np.nan, np.nan, np.nan, 1.0)
    parts.append(trajectory(core, out, 20))
    core.no_collision(["a", "b"])
    core.set_param("restitution", 0.5)
    inp["joint_force"][:] = -0.2
    inp["a.velocity"][:] = np.nan
    inp["b.velocity"][:] = (np.nan, -0.1, np.nan, np.nan, np.nan, np.nan)
    parts.append(trajectory(core, out, 20))
    core.make(["a", "b", "c", "arm", "floor"])
    parts.append(trajectory(core, out, 20))
    return np.concatenate(parts)


def rest_inputs(inp) -> None:
    """Every input back at its start value (as the bus holds it when a run starts)."""
    inp["joint_force"][:] = 0.0
    inp["body_wrench"][:] = 0.0
    inp["body_velocity"][:] = np.nan


@ENGINES
def test_save_restore_is_bit_exact_across_edits_and_params(engine):
    core, inp, out = make_core(engine, *scene_for_state())
    run(core, 30)
    saved, params = core.get_state(), core.params
    plain = trajectory(core, out, 40)
    core.set_state(saved)
    first = edited_run(core, inp, out)
    after, after_params = core.get_state(), core.params
    tail = trajectory(core, out, 30)
    # back before every edit: the original structure and parameters, then replay
    core.restore_param_state(dict(params))
    core.set_state(saved)
    rest_inputs(inp)
    assert core.selection == tuple(core.objects())
    assert np.array_equal(trajectory(core, out, 40), plain)
    core.set_state(saved)
    assert np.array_equal(edited_run(core, inp, out), first)
    # forward again into the edited structure
    core.restore_param_state(dict(params))
    core.set_state(saved)
    core.restore_param_state(dict(after_params))
    core.set_state(after)
    assert np.array_equal(trajectory(core, out, 30), tail)


@ENGINES
def test_no_collision_lets_a_box_fall_through_another(engine):
    scene = (FLOOR, box("low", (0.3, 0.3, 0.1), (0, 0, 0.05), joint=JointSpec("fixed")),
             box("drop", (0.1, 0.1, 0.1), (0, 0, 0.4), mass=0.1))
    core, _, out = make_core(engine, *scene)
    run(core, 400)
    assert out["drop.pos"][2] == pytest.approx(0.15, abs=2e-3)  # on top of the low box
    core, _, out = make_core(engine, *scene)
    core.no_collision(["low", "drop"])
    run(core, 400)
    assert out["drop.pos"][2] == pytest.approx(0.05, abs=2e-3)  # through it, on the floor


@ENGINES
def test_queries_and_fork(engine):
    core, _, out = make_core(engine, *scene_for_state())
    assert core.objects() == ["floor", "a", "b", "c", "arm"]
    assert core.joints() == ["a", "b", "c", "arm"]
    info = core.body_info("a")
    assert info.free and info.parent is None
    assert info.geoms[0]["type"] == "box" and info.geoms[0]["size"] == pytest.approx((0.1, 0.1, 0.1))
    run(core, 50)
    lin, ang = core.body_velocity("c")
    # Exudyn answers from the very state its outputs come from; MuJoCo recomputes (to rounding)
    same = np.array_equal if engine is ExudynCore else np.allclose
    assert same(lin, out["c.linvel"]) and same(ang, out["c.angvel"])
    twin = copy.deepcopy(core)  # what World.fork does
    _, twin_out = bind(twin)
    twin.start(0)
    assert np.array_equal(trajectory(twin, twin_out, 30), trajectory(core, out, 30))
    twin.set_param("gravity", (0.0, 0.0, 0.0))
    run(twin, 10)
    assert core.params["gravity"][2] == -G


@ENGINES
def test_place_moves_a_free_body_at_rest(engine):
    core, _, out = make_core(engine, FLOOR, box("a", (0.1, 0.1, 0.1), (0, 0, 0.5), mass=0.1))
    run(core, 50)
    core.place("a", (1.0, 2.0, 0.3), (0.0, 0.0, 0.0, 1.0))
    assert out["a.pos"] == pytest.approx([1.0, 2.0, 0.3])
    if engine is ExudynCore:  # its rotation parameters give the quaternion up to sign
        assert abs(float(np.dot(out["a.quat"], [0.0, 0.0, 0.0, 1.0]))) == pytest.approx(1.0)
    else:
        assert out["a.quat"] == pytest.approx([0.0, 0.0, 0.0, 1.0])
    assert np.all(out["a.linvel"] == 0.0)
    with pytest.raises(DynabrainError, match="free"):
        core.place("floor", (0, 0, 0))
