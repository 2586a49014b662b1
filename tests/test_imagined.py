"""The imagined futures are visible: a logged run in which a brain runs a batch and a plan and keeps some
branches holds each on its own /imagined/<name>/<branch>/... channels, at the branch's own ticks, read
back with the mcap package; rollbacks (inside and beyond the window) leave them; replay --verify ignores
them. World.imagine checks what it is given and tells every observer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from dynabrain.modules.basic import Sine
from dynabrain.orchestrator import Batch, DynabrainError, Observer, World
from dynabrain.orchestrator.brain.batch import BatchResult
from dynabrain.orchestrator.brain.plan import Action, search
from dynabrain.orchestrator.kernel.branch import BranchStatus
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import read_index
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.scenario.model import load_scenario

SLIDER = Path(__file__).resolve().parent / "scenarios" / "slider.yaml"
DT = 2_000_000
FORCES = (-2.0, 0.0, 2.0)
RECORD = ["core.cart.pos", "core.cart.quat", "core.s.q"]


def read(path: Path, topic: str) -> list:
    """(simulated time, sequence, decoded message) of a topic, with the mcap package and its protobuf
    decoder (the publish time is the simulated time; the log time is the run's wall-clock start plus it)."""
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        return [(m.publish_time, m.sequence, d) for _s, _c, m, d in reader.iter_decoded_messages(topics=[topic])]


def channels(path: Path) -> dict[str, dict[str, str]]:
    with open(path, "rb") as fh:
        return {c.topic: c.metadata for c in make_reader(fh).get_summary().channels.values()}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A brain's logged session on a slider: a batch of three pushes (branches 0 and 2 kept), then a
    plan (kept), then a rollback within the window and one beyond it."""
    tmp = tmp_path_factory.mktemp("imagined")
    sc = load_scenario(SLIDER)
    world = sc.build()
    McapLogger(tmp / "run.mcap", window=8, batch=4).attach(world, sc)
    world.tick(20)
    with Batch(world, backend="processes", workers=2) as batch:
        pushes = batch.run(30, branches=3, inputs={"core.s.force": np.array([np.full(30, f) for f in FORCES])},
                           record=RECORD)
        kept = pushes.imagine(world, "push", branches=[0, 2])
        world.tick(10)
        actions = [Action(f"push {f:+g} N", 25, inputs={"core.s.force": f}) for f in (-4.0, 0.0, 4.0)]
        plan = search(world, actions, record=["core.s.q", "cart.pos", "cart.quat"], batch=batch,
                      heuristic=lambda o: abs(o["core.s.q"] - 0.1), goal=lambda o: abs(o["core.s.q"] - 0.1) < 0.03)
    planned = plan.imagine(world, "plan")
    world.tick(5)
    world.backtick(3)    # within the window
    world.tick(30)
    world.backtick(25)   # beyond it: the file is rewritten at close
    world.tick(10)
    world.close()
    return tmp / "run.mcap", pushes, kept, plan, planned


def test_kept_branches_are_on_their_own_channels_at_their_own_ticks(session):
    path, pushes, kept, _plan, _planned = session
    assert [(k.name, k.branch, k.start_tick, k.ticks) for k in kept] == [("push", 0, 20, 30), ("push", 2, 20, 30)]
    topics = channels(path)
    assert not any(t.startswith("/imagined/push/1/") for t in topics)  # not asked for
    for b in (0, 2):
        meta = topics[f"/imagined/push/{b}/bus"]
        assert (meta["imagined"], meta["branch"], meta["start_tick"]) == ("push", str(b), "20")
        bus = read(path, f"/imagined/push/{b}/bus")
        assert [t for t, _s, _m in bus] == [(20 + k + 1) * DT for k in range(30)]
        assert [m.tick for _t, _s, m in bus] == list(range(21, 51))
        assert all(seq == 0 for _t, seq, _m in bus)  # the epoch when it was imagined
        q = np.array([m.core__s__q for _t, _s, m in bus])
        pos = np.array([list(m.core__cart__pos) for _t, _s, m in bus])
        assert q.tobytes() == pushes.signals["core.s.q"][b].tobytes()
        assert pos.tobytes() == pushes.signals["core.cart.pos"][b].tobytes()
        tf = read(path, f"/imagined/push/{b}/tf")
        assert [t for t, _s, _m in tf] == [t for t, _s, _m in bus]
        frames = [m.transforms[0] for _t, _s, m in tf]
        assert {(f.parent_frame_id, f.child_frame_id) for f in frames} == {("world", f"imagined/push/{b}/cart")}
        assert np.array([[f.translation.x, f.translation.y, f.translation.z] for f in frames]).tobytes() \
            == pos.tobytes()
        origin = read_index(path).info.time_origin_ns  # Foxglove timestamps are log times
        assert frames[-1].timestamp.ToNanoseconds() == origin + 50 * DT
        (when, _s, scene), = read(path, f"/imagined/push/{b}/scene")
        entity, = scene.entities
        assert when == 21 * DT and entity.timestamp.ToNanoseconds() == origin + 21 * DT
        assert entity.frame_id == f"imagined/push/{b}/cart" and entity.frame_locked
        assert entity.lifetime.ToNanoseconds() == 30 * DT and 0 < entity.cubes[0].color.a < 1
    pushed = read(path, "/imagined/push/2/bus")
    assert pushed[-1][2].core__s__q > 0 > read(path, "/imagined/push/0/bus")[-1][2].core__s__q


def test_the_plan_is_kept_from_its_start_tick(session):
    path, _pushes, _kept, plan, planned = session
    assert plan.found and planned is not None and planned.start_tick == 30
    ticks = 25 * len(plan.actions)
    bus = read(path, "/imagined/plan/0/bus")
    assert [t for t, _s, _m in bus] == [(30 + k + 1) * DT for k in range(ticks)]
    assert np.array([m.core__s__q for _t, _s, m in bus]).tobytes() == plan.trajectory["core.s.q"].tobytes()
    assert len(read(path, "/imagined/plan/0/tf")) == ticks
    events = [e for e in read_index(path).events if e["kind"] == "imagined"]
    assert [(e["detail"]["name"], e["detail"]["branch"], e["detail"]["start_tick"], e["tick"]) for e in events] \
        == [("push", 0, 20, 20), ("push", 2, 20, 20), ("plan", 0, 30, 30)]
    assert events[-1]["detail"]["topic"] == "/imagined/plan/0" and events[-1]["detail"]["bodies"] == ["cart"]


def test_rollbacks_leave_what_was_imagined_and_verify_ignores_it(session):
    path, _pushes, _kept, plan, _planned = session
    topics = channels(path)
    assert "/discarded/bus" in topics and not any(t.startswith("/discarded/imagined") for t in topics)
    assert len(read(path, "/imagined/plan/0/bus")) == 25 * len(plan.actions)  # the file was rewritten: all kept
    index = read_index(path)
    assert not any(k.startswith("/imagined") for k in index.keys)
    result = verify(path)
    assert result.ok and result.last_tick == 47


class Seen(Observer):
    def __init__(self):
        self.imagined = []

    def on_imagined(self, view, imagined):
        self.imagined.append((view.tick, imagined))


@pytest.fixture
def wave():
    world = World("w", step="1ms")
    world.add_module(Sine("wave", amplitude=1.0, frequency=2.0))
    world.tick(3)
    yield world
    world.close()


def test_world_imagine_tells_every_observer_a_read_only_copy(wave):
    seen = Seen()
    wave.observe(seen)
    values = np.arange(4.0)
    made = wave.imagine("guess", 2, {"wave.y": values, "cost": np.ones((4, 2))}, branch=5)
    values[0] = 99.0
    (tick, got), = seen.imagined
    assert got is made and tick == 3 and (got.name, got.branch, got.start_tick, got.ticks, got.dt_ns) \
        == ("guess", 5, 2, 4, 1_000_000)
    assert got.signals["wave.y"].tolist() == [0.0, 1.0, 2.0, 3.0] and not got.signals["wave.y"].flags.writeable
    assert got.units == {"wave.y": "1", "cost": ""} and "signals" not in repr(got)
    assert wave.tick_count == 3  # the world does not change


@pytest.mark.parametrize(("name", "start", "signals", "message"), [
    ("a/b", 0, {"wave.y": [1.0]}, "letters, digits"),
    ("ok", -1, {"wave.y": [1.0]}, "start_tick must be an integer >= 0"),
    ("ok", 0, {}, "signals is a mapping"),
    ("ok", 0, {"wave.y": np.zeros((2, 3))}, r"wave\.y have shape \(2, 3\)"),
    ("ok", 0, {"wave.y": [1.0, 2.0], "cost": [1.0]}, "the same number"),
    ("ok", 0, {"cost": 1.0}, "the same number"),
    ("ok", 0, {"cost": [[1.0], [1.0, 2.0]]}, "not numbers"),
])
def test_world_imagine_refuses_what_it_cannot_keep(wave, name, start, signals, message):
    with pytest.raises(DynabrainError, match=message):
        wave.imagine(name, start, signals)


def test_a_batch_result_keeps_the_ticks_each_branch_ran(wave):
    seen = Seen()
    wave.observe(seen)
    signals = {"wave.y": np.arange(12.0).reshape(3, 4)}
    status = [BranchStatus(True, ticks_done=4), BranchStatus(False, "boom", 5, ticks_done=2),
              BranchStatus(False, "refused")]
    result = BatchResult(signals, [None, None, None], status, 4, "serial", 0.1)
    kept = result.imagine(wave, "try", start_tick=1)
    assert [(k.branch, k.start_tick, k.signals["wave.y"].tolist()) for k in kept] \
        == [(0, 1, [0.0, 1.0, 2.0, 3.0]), (1, 1, [4.0, 5.0])]  # branch 2 ran no tick
    assert [k.start_tick for k in result.imagine(wave, "now", branches=1)] == [wave.tick_count]
    with pytest.raises(DynabrainError, match="no branch 3"):
        result.imagine(wave, "x", branches=[3])
