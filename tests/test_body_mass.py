"""A body's own mass, set at run time (`World.set_material(mass=...)`, ``world.set("core.<body>.mass", kg)``, a
scenario event, a batch parameter): real MuJoCo feels it (a heavier box slides less far from the same push),
history and forks keep it, None gives the model's own back bit for bit, a logged run with it verifies, and a
mass of zero or below is refused by name."""

from __future__ import annotations

import numpy as np
import pytest

from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator import Batch, BodySpec, DynabrainError, SceneSpec, World

TICKS = 300


def _world() -> World:
    floor = BodySpec(name="floor", shape="plane", size=(), color="grey")
    box = BodySpec(name="box", shape="box", size=(0.1, 0.1, 0.1), pos=(0, 0, 0.0505), mass=0.5, color="red")
    return World("w", step="2ms", history=50, core=MujocoCore("core", SceneSpec(bodies=(floor, box)), friction=0.3))


def _push() -> np.ndarray:
    force = np.zeros((TICKS, 6))
    force[:50, 0] = 3.0  # 3 N for 0.1 s
    return force


def test_a_heavier_box_slides_less_far_and_none_gives_the_models_mass_back():
    with _world() as w:
        start = w.export_state()
        light = w.run(TICKS, inputs={"core.box.wrench": _push()}, record=["core.box.pos"])["core.box.pos"][-1]
        w.import_state(start)
        w.set("core.box.mass", 0.7)
        assert w.get("core.box.mass") == 0.7 and w.core.material("box").mass == 0.7
        assert w.core.mj.model.body("box").mass[0] == pytest.approx(0.7)
        heavy = w.run(TICKS, inputs={"core.box.wrench": _push()}, record=["core.box.pos"])["core.box.pos"][-1]
        assert 0.0 < heavy[0] < 0.8 * light[0]
        w.import_state(start)
        w.set_material("box", mass=None)
        again = w.run(TICKS, inputs={"core.box.wrench": _push()}, record=["core.box.pos"])["core.box.pos"][-1]
        assert again.tobytes() == light.tobytes()


def test_history_forks_and_batches_keep_a_bodys_mass():
    with _world() as w:
        w.tick(5)
        w.set("core.box.mass", 2.0)
        w.tick(5)
        twin = w.fork()
        try:
            assert twin.core.material("box").mass == 2.0
        finally:
            twin.close()
        w.backtick(7)  # before the change
        assert w.core.material("box").mass is None
        assert w.core.mj.model.body("box").mass[0] == pytest.approx(0.5)
        with Batch(w, backend="serial") as batch:
            res = batch.run(TICKS, branches=2, inputs={"core.box.wrench": _push()},
                            params={"core.box.mass": [0.5, 1.0]}, record=["core.box.pos"])
        far = res.signals["core.box.pos"][:, -1, 0]
        assert far[1] < far[0]


def test_a_mass_of_zero_or_below_is_refused_by_name():
    with _world() as w:
        with pytest.raises(DynabrainError, match=r"set_material\('box'\), field mass: mass must be above 0"):
            w.set("core.box.mass", 0.0)
        with Batch(w, backend="serial") as batch, pytest.raises(
                DynabrainError, match=r"params\['core.box.mass'\]\[0\] is -1.0; a body's mass"):
            batch.run(5, branches=1, params={"core.box.mass": [-1.0]})


SCENE = """\
name: heavier
world: {step: 2ms, duration: 0.4s, core: mujoco}
scene:
  - plane: {name: floor}
  - box: {name: box, size: [0.1, 0.1, 0.1], pos: [0, 0, 0.0505], mass: 0.5}
events:
  - {at: 0s, set: {core.box.wrench: [3, 0, 0, 0, 0, 0]}}
  - {at: 0.1s, set: {core.box.wrench: [0, 0, 0, 0, 0, 0], core.box.mass: 0.8}}
"""


def test_a_scenario_event_sets_a_mass_and_the_log_verifies(tmp_path):
    from dynabrain.orchestrator import load_world
    from dynabrain.orchestrator.logs.logger import McapLogger
    from dynabrain.orchestrator.logs.verify import verify
    from dynabrain.orchestrator.scenario.model import load_scenario

    path = tmp_path / "heavier.yaml"
    path.write_text(SCENE)
    log = tmp_path / "heavier.mcap"
    scenario = load_scenario(path)
    with scenario.build() as world:
        logger = McapLogger(log).attach(world, scenario)
        world.tick(200)
        assert world.core.material("box").mass == 0.8
        logger.close()
    result = verify(log)
    assert result.ok, result.divergence
    bad = tmp_path / "bad.yaml"
    bad.write_text(SCENE.replace("core.box.mass: 0.8", "core.box.mass: 0"))
    with pytest.raises(DynabrainError, match=r"bad.yaml:8 .*mass is above 0 kg"):
        load_world(bad)
