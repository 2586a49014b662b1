"""MCAP logging with the real MuJoCo core: what the file holds is what the world had, the Foxglove
schemas decode with the foxglove schema package and with the mcap package's protobuf decoder, and
rollbacks leave the run on the main topics and the discarded ticks on /discarded/..."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory

from dynabrain.modules.basic import Noise, Sine
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.logs import logger as mcap_logger
from dynabrain.orchestrator.logs import shared_rows
from dynabrain.orchestrator.logs import sink as mcap_sink
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import final_mask, iter_bus, read_index
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"


def record(tmp_path: Path, name: str = "two_cubes", **kw):
    sc = load_scenario(SCENARIOS / f"{name}.yaml")
    world = sc.build()
    McapLogger(tmp_path / "run.mcap", **kw).attach(world, sc)
    return world, tmp_path / "run.mcap"


def messages(path: Path, topic: str, cls=None, *, log_time: bool = False):
    """(simulated time, sequence, message) of a topic, read with the mcap package (an independent reader):
    the publish time, or with ``log_time`` the log time (the wall-clock start plus the simulated time)."""
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        return [(m.log_time if log_time else m.publish_time, m.sequence, cls.FromString(m.data) if cls else m.data)
                for _s, _c, m in reader.iter_messages(topics=[topic], log_time_order=False)]


@pytest.mark.parametrize("writer", ["process", "thread"])
def test_round_trip_holds_what_the_world_had(tmp_path, writer):
    world, path = record(tmp_path, decimate=5, writer=writer)
    seen = {0: world.snapshot().bus}
    poses = {}
    for _ in range(120):
        world.tick()
        seen[world.tick_count] = world.snapshot().bus
        poses[world.tick_count] = {b: world.core.body_pose(b) for b in world.core.bodies()}
    world.set("core.friction", 0.3)
    world.close()

    index = read_index(path)
    rows = {r.tick: r.row for r in iter_bus(path, index)}
    assert sorted(rows) == list(range(121))
    for tick, bus in seen.items():
        assert rows[tick].tobytes() == bus.tobytes(), tick  # bit for bit

    tf = messages(path, "/tf", FrameTransforms)
    assert [t for t, _s, _m in tf] == [k * 2_000_000 for k in range(0, 121, 5)]
    origin = index.info.time_origin_ns
    assert abs(origin - time.time_ns()) < 600e9  # the run's wall-clock start, not 1970
    assert [t for t, _s, _m in messages(path, "/tf", log_time=True)] == [origin + t for t, _s, _m in tf]
    for sim_time, _seq, msg in tf[1:]:
        tick, log_time = sim_time // 2_000_000, origin + sim_time
        assert {t.child_frame_id for t in msg.transforms} == {"floor", "aa", "bb"}
        for t in msg.transforms:
            pos, quat = poses[tick][t.child_frame_id]
            assert t.parent_frame_id == "world" and t.timestamp.ToNanoseconds() == log_time
            assert [t.translation.x, t.translation.y, t.translation.z] == pos.tolist()
            assert [t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z] == quat.tolist()

    info = index.info
    assert info.scenario_name == "two_cubes" and "box: {name: aa" in info.scenario_text
    assert info.seed == 0 and info.dt_ns == 2_000_000 and info.start_time and "mujoco" in info.versions
    param = [e for e in index.events if e["kind"] == "param"]
    assert param == [{"seq": param[0]["seq"], "tick": 120, "time": 0.24, "epoch": 0, "kind": "param",
                      "source": "api", "detail": {"name": "core.friction", "value": 0.3}}]


def test_file_is_valid_mcap_and_every_schema_decodes(tmp_path):
    world, path = record(tmp_path, chunk_bytes=20_000)
    world.tick(200)
    world.close()
    for _ in StreamReader(open(path, "rb"), validate_crcs=True).records:  # noqa: SIM115
        pass
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary.statistics.chunk_count > 3
        decoded = {}
        for _schema, channel, message, value in reader.iter_decoded_messages(topics=["/bus", "/tf", "/scene"]):
            decoded.setdefault(channel.topic, []).append((message.publish_time, value))
    assert len(decoded["/bus"]) == len(decoded["/tf"]) == 201 and len(decoded["/scene"]) == 1
    bus_schema = next(sc for sc in summary.schemas.values() if sc.name == "dynabrain.layout1.Bus")
    assert not any(f.HasField("source_code_info") for f in FileDescriptorSet.FromString(bus_schema.data).file)
    units = json.loads(next(c for c in summary.channels.values() if c.topic == "/bus").metadata["units"])
    assert units["core.aa.pos"] == "m" and units["core.aa.angvel"] == "rad/s"  # strict readers refuse comments
    t, bus = decoded["/bus"][150]
    assert bus.tick == 150 and bus.epoch == 0 and bus.time == 0.3 and t == 150 * 2_000_000
    world2 = load_scenario(SCENARIOS / "two_cubes.yaml").build()
    world2.tick(150)
    assert list(bus.core__aa__pos) == world2.get("aa.pos").tolist()
    world2.close()

    scene = messages(path, "/scene", SceneUpdate)[0][2]
    by_id = {e.id: e for e in scene.entities}
    assert set(by_id) == {"floor", "aa", "bb"}
    assert by_id["aa"].frame_locked and by_id["aa"].frame_id == "aa"
    cube = by_id["bb"].cubes[0]
    assert (cube.size.x, cube.size.y, cube.size.z) == pytest.approx((0.2, 0.2, 0.15))
    assert cube.color.a == 1.0 and by_id["floor"].cubes[0].size.x == pytest.approx(4.0)


@pytest.mark.parametrize("writer", ["process", "thread"])
def test_rollbacks_leave_the_run_on_the_main_topics(tmp_path, writer):
    world, path = record(tmp_path, window=16, batch=8, writer=writer)
    world.tick(100)
    world.backtick(10)          # within the window: never written to /bus
    world.set("core.friction", 0.4)
    world.tick(60)              # to 150
    world.backtick(80)          # reaches ticks already written: the file is rewritten on close
    world.tick(30)              # to 100
    final = {}
    world.backtick(30)
    for _ in range(30):
        world.tick()
        final[world.tick_count] = world.snapshot().bus
    world.close()

    index = read_index(path)
    bus = {}
    for row in iter_bus(path, index):
        bus.setdefault(row.topic, []).append((row.epoch, row.tick, row.row))
    main = bus["/bus"]
    assert [t for _e, t, _r in main] == list(range(101))  # the run, each tick once
    for epoch, tick, row in main:
        if tick > 70:
            assert epoch == 3 and row.tobytes() == final[tick].tobytes()
    discarded = sorted((e, t) for e, t, _r in bus["/discarded/bus"])
    assert discarded == ([(0, t) for t in range(71, 101)] + [(1, t) for t in range(91, 151)]
                         + [(2, t) for t in range(71, 101)])
    rollbacks = [e["detail"] for e in index.events if e["kind"] == "rollback"]
    assert [(r["from_tick"], r["to_tick"], r["cause"]) for r in rollbacks] == [
        (100, 90, "backtick"), (150, 70, "backtick"), (100, 70, "backtick")]
    assert len(messages(path, "/tf")) == 101


def test_restore_and_failed_ticks_are_rollbacks_too(tmp_path):
    world, path = record(tmp_path, window=0, batch=4)
    world.tick(20)
    snap = world.snapshot()
    world.tick(30)
    world.restore(snap)
    world.tick(5)
    world.close()
    index = read_index(path)
    rollbacks = [e["detail"] for e in index.events if e["kind"] == "rollback"]
    assert rollbacks == [{"from_tick": 50, "to_tick": 20, "cause": "restore", "epoch": 1, "snapshot": 1}]
    run = [(r.epoch, r.tick) for r in iter_bus(path, index) if r.topic == "/bus"]
    assert run == [(0, t) for t in range(20)] + [(1, t) for t in range(20, 26)]


def test_modules_arriving_and_leaving_change_the_layout(tmp_path):
    world, path = record(tmp_path)
    world.tick(10)
    world.add_module(Sine("wave", frequency=2.0))
    world.add_module(Noise("noise", n=2))
    world.tick(10)
    world.remove_module("wave")
    world.tick(10)
    world.close()
    index = read_index(path)
    layouts = [e["detail"] for e in index.events if e["kind"] == "layout"]
    assert [d["layout"] for d in layouts] == [1, 2, 3]
    assert layouts[1]["added"] == ["noise.y", "wave.y"] and layouts[2]["removed"] == ["wave.y"]
    codecs, numbers = {}, {}
    for r in iter_bus(path, index):
        codecs.setdefault(r.codec.key, []).append(r.tick)
        numbers[r.codec.key] = r.codec.numbers["core.aa.pos"]
        if r.codec.key == 2:
            assert "wave.y" in r.codec.by_name
    assert numbers[1] == numbers[2] == numbers[3]  # a signal keeps its field number in every layout
    assert codecs == {1: list(range(11)), 2: list(range(11, 21)), 3: list(range(21, 31))}
    topics = {index.channels[c].topic: index.bus_codec(c).key
              for c in index.channels if index.is_bus(c)}
    assert topics == {"/bus": 1, "/bus/layout2": 2, "/bus/layout3": 3}  # one schema per topic
    assert [d["topic"] for d in layouts] == ["/bus", "/bus/layout2", "/bus/layout3"]


def test_scene_draws_every_shape_and_meshes(tmp_path):
    (tmp_path / "model.xml").write_text("""<mujoco>
  <asset><mesh name="tet" vertex="0 0 0  0.1 0 0  0 0.1 0  0 0 0.1"/></asset>
  <worldbody>
    <geom name="ground" type="plane" size="1 1 0.1"/>
    <body name="thing" pos="0 0 1"><freejoint/>
      <geom type="mesh" mesh="tet"/>
      <geom type="capsule" size="0.02 0.1" pos="0.3 0 0"/>
      <geom type="cylinder" size="0.03 0.05" pos="-0.3 0 0"/>
      <geom type="sphere" size="0.05" pos="0 0.3 0"/>
      <geom type="box" size="0.1 0.1 0.1" pos="0 -0.3 0"/>
    </body>
  </worldbody>
</mujoco>""")
    (tmp_path / "mesh.yaml").write_text("name: mesh\nworld: {step: 2ms, duration: 0.1s}\nscene: {model: model.xml}\n")
    sc = load_scenario(tmp_path / "mesh.yaml")
    world = sc.build()
    McapLogger(tmp_path / "mesh.mcap").attach(world, sc)
    world.tick(3)
    world.close()
    scene = messages(tmp_path / "mesh.mcap", "/scene", SceneUpdate)[0][2]
    thing = next(e for e in scene.entities if e.id == "thing")
    assert (len(thing.triangles), len(thing.cylinders), len(thing.spheres), len(thing.cubes)) == (1, 2, 3, 1)
    tri = thing.triangles[0]
    assert len(tri.points) == 4 and len(tri.indices) == 12 and max(tri.indices) == 3
    ends = sorted(s.pose.position.x for s in thing.spheres if s.size.x == pytest.approx(0.04))
    assert ends == pytest.approx([0.3, 0.3]) and len({s.pose.position.z for s in thing.spheres}) == 3
    ground = next(e for e in scene.entities if e.id == "world")  # a geom of the world body: its own entity
    assert ground.frame_id == "world" and ground.cubes[0].size.x == pytest.approx(2.0)


def test_frozen_bodies_are_drawn_translucent_and_many_bodies_encode(tmp_path):
    world, path = record(tmp_path, name="selection")
    world.tick(3)
    world.close()
    scene = messages(path, "/scene", SceneUpdate)[0][2]
    alpha = {e.id: e.cubes[0].color.a for e in scene.entities}
    assert alpha["box_0_0"] == 1.0 and alpha["box_1_0"] == pytest.approx(0.35)
    tf = messages(path, "/tf", FrameTransforms)
    assert len(tf[-1][2].transforms) == 201  # the floor and 200 boxes, in the many-bodies encoding
    frozen = next(t for t in tf[-1][2].transforms if t.child_frame_id == "box_3_3")
    assert frozen.translation.z == 0.3


def test_final_mask_follows_rollbacks():
    # ticks 1..5 (epoch 0); back to 2; 3..4 (epoch 1); restore to 3 (epoch 2): 3..4
    keys = [(0, t) for t in range(1, 6)] + [(1, 3), (1, 4)] + [(2, 3), (2, 4)]
    mask = final_mask(keys, {0: 2, 1: 3})
    assert [k for k, m in zip(keys, mask, strict=True) if m] == [(0, 1), (0, 2), (2, 3), (2, 4)]
    assert final_mask([(0, 1), (0, 2), (0, 3)], {0: 1}).tolist() == [True, False, False]


def test_a_log_that_cannot_be_written_is_a_clear_error(tmp_path):
    with pytest.raises(DynabrainError, match=r"cannot write the log .*nowhere.*No such file"):
        record(tmp_path / "nowhere")
    with pytest.raises(DynabrainError, match="decimate must be an integer >= 1"):
        McapLogger(tmp_path / "x.mcap", decimate=0)


def test_small_blocks_and_uneven_windows_keep_every_tick_in_order(tmp_path, monkeypatch):
    # blocks of 3 rows, drains of 5 rows 7 ticks behind: drains and rollbacks cut blocks anywhere
    monkeypatch.setattr(mcap_logger, "BLOCK_BYTES", 3 * 8 * 39)
    world, path = record(tmp_path, window=7, batch=5, decimate=2)
    seen = {}

    def tick(n):
        for _ in range(n):
            world.tick()
            seen[world.tick_count] = world.snapshot().bus

    tick(23)
    world.backtick(4)   # within the window
    tick(9)             # to 28
    world.backtick(13)  # to 15: reaches written ticks
    tick(11)            # to 26
    world.close()
    index = read_index(path)
    rows = [(r.topic, r.epoch, r.tick, r.row) for r in iter_bus(path, index)]
    main = [(e, t) for topic, e, t, _r in rows if topic == "/bus"]
    assert main == [(0, t) for t in range(16)] + [(2, t) for t in range(16, 27)]
    assert all(r.tobytes() == seen[t].tobytes() for topic, _e, t, r in rows if topic == "/bus" and t > 15)
    discarded = sorted((e, t) for topic, e, t, _r in rows if topic == "/discarded/bus")
    assert discarded == [(0, t) for t in range(16, 24)] + [(1, t) for t in range(20, 29)]
    assert [m[0] // 2_000_000 for m in messages(path, "/tf")] == list(range(0, 27, 2))


def test_a_failure_on_the_writers_thread_reaches_the_caller(tmp_path, monkeypatch, caplog):
    world, _path = record(tmp_path, window=0, batch=4, writer="thread")

    def broken(*_args):
        raise OSError("disk on fire")

    monkeypatch.setattr(mcap_sink.LogSink, "rows", broken)
    with pytest.raises(DynabrainError, match=r"writing the log .*OSError: disk on fire"):
        world.tick(40)  # the batch fails on the writer's thread; the next hand-over reports it
    world.close()       # the world keeps closing; the log says why the file is incomplete
    assert "closing the MCAP log" in caplog.text and "disk on fire" in caplog.text


def test_the_loss_of_the_writer_process_reaches_the_caller(tmp_path, caplog):
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    logger = McapLogger(tmp_path / "run.mcap", window=0, batch=4).attach(world, sc)
    world.tick(10)
    logger._sink._proc.kill()  # the child writer dies (killed, out of memory, ...)
    logger._sink._proc.wait()
    with pytest.raises(DynabrainError, match=r"the log writer process for .*run.mcap (is gone|ended).*signal 9"):
        world.tick(40)
    assert world.tick_count >= 10  # the simulation itself is fine
    world.close()
    assert "closing the MCAP log" in caplog.text


def test_shared_rows_fall_back_when_shared_memory_is_full(tmp_path, monkeypatch):
    full, spare = tmp_path / "full", tmp_path / "spare"
    full.mkdir()
    spare.mkdir()
    real = shared_rows._reserve

    def reserve(folder, size):
        if folder == str(full):
            raise OSError(28, "No space left on device")  # what posix_fallocate says on a full tmpfs
        return real(folder, size)

    monkeypatch.setattr(shared_rows, "_reserve", reserve)
    monkeypatch.setattr(shared_rows, "_row_folders", lambda: [str(full), str(spare)])
    rows = shared_rows.SharedRows((4, 3))
    assert os.path.dirname(rows.path) == str(spare) and rows.array.shape == (4, 3)
    rows.array[:] = 1.5
    rows.release()
    monkeypatch.setattr(shared_rows, "_row_folders", lambda: [str(full)])
    with pytest.raises(DynabrainError, match=r"no memory to share rows with the log writer.*No space left"):
        shared_rows.SharedRows((4, 3))
    assert list(full.iterdir()) == [] and list(spare.iterdir()) == []


def test_the_writer_process_finishes_the_file_when_the_simulation_vanishes(tmp_path):
    """The simulation's end of the pipe closes while the child still has batches to write and answers
    to send (as when its process is killed): the child writes them all and finishes the file."""
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    logger = McapLogger(tmp_path / "run.mcap", window=0, batch=4).attach(world, sc)
    world.tick(400)  # a hundred batches handed over, most not yet acknowledged
    sink = logger._sink
    sink._conn.close()  # no `finish`: the pipe just closes
    sink._proc.wait(30)
    assert sink._proc.returncode == 0
    index = read_index(tmp_path / "run.mcap")  # complete: summary, footer, every handed-over tick
    ticks = sorted(r.tick for r in iter_bus(tmp_path / "run.mcap", index))
    assert ticks == list(range(len(ticks))) and len(ticks) >= 397
    world.unobserve(logger)
    world.close()


@pytest.mark.parametrize("writer", ["process", "thread"])
def test_a_writer_that_falls_behind_makes_the_simulation_wait_not_lose(tmp_path, monkeypatch, writer):
    # two blocks of 3 rows at most, handed over a row at a time: the stepping thread keeps waiting
    # for the writer to give a block back, and every tick still arrives, in order
    monkeypatch.setattr(mcap_logger, "BLOCK_BYTES", 3 * 8 * 39)
    monkeypatch.setattr(mcap_logger, "MAX_BLOCKS", 2)
    world, path = record(tmp_path, window=0, batch=1, writer=writer)
    world.tick(300)
    world.close()
    ticks = [r.tick for r in iter_bus(path, read_index(path)) if r.topic == "/bus"]
    assert ticks == list(range(301))
