"""`replay --verify`: a recording with rollbacks, restores, a failed tick, parameter and input edits
and modules arriving and leaving (Python classes, and FMUs built from source, in process or isolated)
re-simulates bit for bit; a doctored recording fails at the tick that was changed, naming the signal
and both values."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from dynabrain.modules.basic import Gain, Noise, Sine
from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.kernel.module import Module, Param, Port
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import read_index
from dynabrain.orchestrator.logs.scan import Channel, LogError, Message, Metadata, Schema, scan
from dynabrain.orchestrator.logs.schema import BusCodec
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.logs.write import McapWriter
from dynabrain.orchestrator.scenario.make import make_module
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"


class Fuse(Module):
    """Counts its steps; its step fails while the run-time parameter ``blown`` is true."""

    PARAMS = (Param("blown", False, runtime=True),)

    def outputs(self):
        return (Port("count", ()),)

    def start(self, t_ns):
        self.count = 0

    def step(self, t_ns, dt_ns):
        if self.params["blown"]:
            raise RuntimeError("the fuse is blown")
        self.count += 1
        self.out["count"][...] = self.count

    def get_state(self):
        return self.count

    def set_state(self, state):
        self.count = state


def busy_run(path: Path, window: int = 8) -> int:
    """A brain's session on two_cubes: every kind of recorded edit and rollback. Returns bus rows made."""
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    McapLogger(path, window=window, batch=4).attach(world, sc)
    world.tick(40)
    world.set("core.friction", 0.5)
    world.add_module(Noise("noise", n=3, sigma=0.1))
    world.add_module(Sine("wave", amplitude=2.0, frequency=3.0))
    world.add_module(Gain("gain", n=3, k=2.0), connect=[("noise.y", "gain.u")])
    world.tick(30)
    world.backtick(5)                      # within the window
    world.disconnect("gain.u")             # an input can be set once nothing drives it
    world.set("gain.u", [1.0, 2.0, 3.0])
    world.tick(25)
    world.backtick(20)                     # beyond the window: written ticks are superseded
    world.make(["aa"])
    world.tick(20)
    snap = world.snapshot()
    world.place("aa", [0.5, 0.0, 0.5])
    world.tick(15)
    world.restore(snap)                    # back to the snapshot, another branch
    world.add_module(Fuse("fuse"))
    world.tick(5)
    world.set("fuse.blown", True)
    with pytest.raises(Exception, match="the fuse is blown"):
        world.tick()                       # a failed tick is rolled back
    world.set("fuse.blown", False)
    world.remove_module("wave")
    world.set("core.restitution", 0.6)
    world.tick(20)
    world.close()
    return 1 + 40 + 30 + 25 + 20 + 15 + 1 + 5 + 20


def test_verify_passes_on_a_run_with_rollbacks_edits_and_modules(tmp_path):
    path = tmp_path / "busy.mcap"
    rows = busy_run(path)
    index = read_index(path)
    kinds = [e["kind"] for e in index.events]
    for kind in ("param", "set", "module_added", "module_removed", "disconnect", "make", "place", "restore",
                 "error", "rollback"):
        assert kind in kinds, kind
    with pytest.raises(LogError, match=f"module class '{Fuse.__module__}:Fuse' is not allowed"):
        verify(path)  # a class of the log's own is made only when allowed, as a scenario's would be
    result = verify(path, allow_python=[Fuse.__module__])
    assert result.ok, result.divergence
    assert result.rows == rows and result.epochs == 4 and result.last_tick == 115
    assert result.ticks == rows - 2  # every row but the first and the one the restore brought back
    seen: list[tuple[int, int]] = []
    again = verify(path, allow_python=[Fuse.__module__], progress=lambda done, total: seen.append((done, total)))
    assert again.ok and seen[-1] == (rows, rows)  # told as it goes, and at the end: every recorded row compared


def test_verify_passes_on_a_cli_run_and_fails_on_a_doctored_file(tmp_path):
    runner = CliRunner()
    path = tmp_path / "cubes.mcap"
    done = runner.invoke(app, ["run", str(SCENARIOS / "two_cubes.yaml"), "--log", str(path), "-q"])
    assert done.exit_code == 0, done.output
    ok = runner.invoke(app, ["replay", str(path), "--verify"])
    assert ok.exit_code == 0, ok.output
    assert "verify: identical up to tick 2500" in ok.output and "ticks/s" in ok.output

    doctored = tmp_path / "doctored.mcap"
    change_bus_value(path, doctored, tick=1234, signal="core.bb.pos", component=2, delta=1e-12)
    result = verify(doctored)
    d = result.divergence
    assert not result.ok and d.tick == 1234 and d.signal == "core.bb.pos" and "component 2" in d.message
    assert d.recorded[2] - d.replayed[2] == pytest.approx(1e-12) and d.recorded[:2] == d.replayed[:2]
    failed = runner.invoke(app, ["replay", str(doctored), "--verify"])
    assert failed.exit_code == 1
    assert "DIVERGES at tick 1234" in failed.output and "core.bb.pos: recorded" in failed.output


ARMS = """\
name: arms
world: {step: 2ms, duration: 2s, core: mujoco}
scene:
  - plane: {name: ground, color: grey}
  - capsule: {name: arm1, size: [0.02, 0.4], mass: 0.5, pos: [0, 0, 1.0], color: blue,
              joint: {hinge: {name: j1, axis: [0, 1, 0], anchor: [0, 0, 0.2], damping: 0.01}}}
  - capsule: {name: arm2, size: [0.02, 0.4], mass: 0.5, pos: [0.5, 0, 1.0], color: orange,
              joint: {hinge: {name: j2, axis: [0, 1, 0], anchor: [0, 0, 0.2], damping: 0.01}}}
"""
"""Two hanging arms and no module: the servo FMU that holds them arrives through the API."""


@pytest.mark.usefixtures("fmu_cache")
@pytest.mark.parametrize("isolate", [False, True], ids=["in_process", "isolated"])
def test_verify_passes_on_a_run_that_added_an_fmu_through_the_api(tmp_path, isolate):
    folder = tmp_path / "scenario"
    shutil.copytree(SCENARIOS.parent / "fmus" / "servo", folder / "fmus" / "servo")  # named relative to it
    (folder / "arms.yaml").write_text(ARMS)
    path = tmp_path / "arms.mcap"
    sc = load_scenario(folder / "arms.yaml")
    world = sc.build()
    McapLogger(path, window=8, batch=4).attach(world, sc)
    world.tick(20)
    spec = {"name": "servo", "fmu": "fmus/servo", "params": {"kp": 20, "kd": 1, "tau_max": 5, "lag": "10ms"},
            **({"isolate": True} if isolate else {})}
    joints = [("core.j1.q", "servo.q[1]"), ("core.j2.q", "servo.q[2]"), ("core.j1.qd", "servo.qd[1]"),
              ("core.j2.qd", "servo.qd[2]"), ("servo.tau[1]", "core.j1.force"), ("servo.tau[2]", "core.j2.force")]
    world.add_module(make_module(spec, base_dir=str(folder)), connect=joints)
    assert (getattr(world.modules["servo"], "pid", None) is not None) is isolate  # its own process, or none
    world.set("servo.q_ref", [0.5, -0.5])
    world.tick(30)
    world.backtick(12)                      # across the FMU's state: the run goes on from tick 38
    world.set("servo.tau_max", 0.6)
    world.tick(25)
    moved = world.get("core.j1.q")
    world.close()
    assert abs(moved) > 1e-3  # the servo drove the arm: its outputs reach the physics

    added = [e["detail"]["spec"] for e in read_index(path).events if e["kind"] == "module_added"]
    assert added == [{**spec, "params": added[0]["params"], "period": "2000000ns",
                      "connect": [list(c) for c in joints]}]
    done = CliRunner().invoke(app, ["replay", str(path), "--verify"])
    assert done.exit_code == 0, done.output
    assert "verify: identical up to tick 63" in done.output, done.output


def change_bus_value(src: Path, dst: Path, *, tick: int, signal: str, component: int, delta: float) -> None:
    """Copy a log, adding ``delta`` to one value of one bus message."""
    writer = McapWriter(dst)
    codecs: dict[int, BusCodec] = {}
    for rec in scan(src):
        if isinstance(rec, Metadata):
            writer.add_metadata(rec.name, rec.values)
        elif isinstance(rec, Schema):
            writer.add_schema(rec.name, rec.encoding, rec.data, schema_id=rec.id)
        elif isinstance(rec, Channel):
            writer.add_channel(rec.topic, rec.encoding, rec.schema_id, rec.metadata, channel_id=rec.id)
            if "layout" in rec.metadata:
                codecs[rec.id] = BusCodec.from_metadata(rec.metadata)
        elif isinstance(rec, Message):
            data = rec.data
            codec = codecs.get(rec.channel_id)
            if codec is not None and rec.publish_time == tick * 2_000_000:
                rows, ticks, epochs = codec.decode(np.frombuffer(data, dtype=np.uint8))
                rows[0, codec.by_name[signal].offset + component] += delta
                data = codec.encode(rows, ticks, epochs, 2_000_000)[0].tobytes()
            writer.add_message(rec.channel_id, rec.log_time, data, rec.sequence, rec.publish_time)
    writer.finish()
