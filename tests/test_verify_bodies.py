"""`replay --verify` of body edits a brain made through the API (issue 14): bodies added (a box, and a
mesh from a file the replay does not need) and removed, a body's own material changed, hinge and slider
joints made with an axis and an anchor, a backtick across them; on both cores the recording re-simulates
bit for bit. The recorded spec is plain values: a damaged one is refused by name, never run."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import read_index
from dynabrain.orchestrator.logs.verify import apply_edit, verify
from dynabrain.orchestrator.scenario.model import load_scenario

SCENE = """\
name: grow
world: {{step: 2ms, core: {engine}, duration: 1s}}
scene:
  - plane: {{name: floor}}
  - box: {{name: base, size: [0.2, 0.2, 0.1], pos: [0, 0, 0.05], mass: 2}}
"""
TETRA = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def api_session(folder, engine: str):
    """A brain's session of body edits on a small scene, logged; returns the log's path."""
    (folder / "grow.yaml").write_text(SCENE.format(engine=engine))
    (folder / "tetra.obj").write_text(TETRA)
    path = folder / "grow.mcap"
    sc = load_scenario(folder / "grow.yaml")
    world: World = sc.build()
    McapLogger(path, window=8, batch=4).attach(world, sc)
    world.tick(10)
    world.add_body(name="lid", shape="box", size=["100mm", "100mm", "20mm"], pos=[0, 0, "0.2m"], mass="100g",
                   color="blue", friction=0.3)
    world.add_body(name="tetra", shape="mesh", mesh=str(folder / "tetra.obj"), scale=1.5, pos=[0.4, 0, 0.1],
                   mass=0.05, restitution=0.2)
    world.tick(20)
    world.set_material("lid", friction=0.9, restitution=0.4)
    world.make_joint("base", "lid", "flap", kind="hinge", axis=[0, 1, 0], anchor=[0.05, 0, "0.12m"])
    world.tick(15)
    world.set("core.tetra.restitution", 0.6)
    world.make_joint("base", "tetra", kind="slider", axis=[1, 0, 0])
    world.tick(15)
    world.backtick(8)                     # across the slider: the run goes on from there
    world.remove_body("tetra")
    world.tick(12)
    world.close()
    (folder / "tetra.obj").unlink()       # the replay needs the recorded vertices, not the file
    return path


@pytest.mark.parametrize("engine", ["mujoco", "exudyn"])
def test_verify_replays_api_bodies_materials_and_joints_bit_for_bit(tmp_path, engine):
    path = api_session(tmp_path, engine)
    kinds = [e["kind"] for e in read_index(path).events if e.get("source") == "api"]
    for kind in ("body_added", "material", "make_joint", "body_removed", "rollback"):
        assert kind in kinds, kinds
    result = verify(path)
    assert result.ok, result.divergence
    assert result.ticks >= 60 and result.rows >= 60
    if engine == "mujoco":  # and through the command line, once
        done = CliRunner().invoke(app, ["replay", str(path), "--verify"])
        assert done.exit_code == 0 and "verify: identical" in done.output, done.output


def test_a_replay_without_the_joint_kind_would_diverge(tmp_path, monkeypatch):
    """The check has teeth: the same log, its hinge replayed as a weld, diverges where the joint was made."""
    path = api_session(tmp_path, "mujoco")
    events = read_index(path).events
    joint = next(e for e in events if e["kind"] == "make_joint")
    assert joint["detail"]["kind"] == "hinge" and joint["detail"]["axis"] == [0.0, 1.0, 0.0]
    import dynabrain.orchestrator.logs.verify as v

    real = v.apply_edit

    def as_weld(world, kind, d, *args, **kwargs):
        if kind == "make_joint":
            d = {k: x for k, x in d.items() if k not in ("kind", "axis", "anchor")}
        return real(world, kind, d, *args, **kwargs)

    monkeypatch.setattr(v, "apply_edit", as_weld)
    result = verify(path)
    assert not result.ok and result.divergence.tick > joint["tick"]


def test_a_damaged_recorded_body_is_refused_and_runs_nothing(tmp_path):
    (tmp_path / "grow.yaml").write_text(SCENE.format(engine="mujoco"))
    world = load_scenario(tmp_path / "grow.yaml").build()
    before = world.core.bodies()
    for spec in ({"name": "x", "shape": "box", "size": [0.1] * 3, "__reduce__": "os.system"},
                 {"name": "x", "shape": "mesh", "mesh": "/etc/passwd"},
                 {"name": "x", "shape": "box", "size": [0.1] * 3, "joint": {"kind": "free", "code": 1}}):
        with pytest.raises(DynabrainError, match=r"the recording's body_added \('x'\).*damaged"):
            apply_edit(world, "body_added", {"body": "x", "spec": json.loads(json.dumps(spec))})
    assert world.core.bodies() == before
    world.close()

