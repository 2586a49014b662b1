"""Logs that strict MCAP readers accept: messages in log-time order in the file (within and across
chunks), one schema per topic, events as ``foxglove.Log``, log times anchored to the run's wall-clock
start with the simulated time kept as the publish time. Read with the ``mcap`` package (an independent
reader), in file order."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.Log_pb2 import Log
from mcap.reader import make_reader
from typer.testing import CliRunner

from dynabrain.modules.basic import Noise, Sine
from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import read_index
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
DT = 2_000_000


def file_order(path: Path) -> list[tuple[str, int, int, int, bytes]]:
    """(topic, schema id, log time, publish time, data) of every message, in file order."""
    with open(path, "rb") as fh:
        return [(c.topic, c.schema_id, m.log_time, m.publish_time, m.data)
                for _s, c, m in make_reader(fh).iter_messages(log_time_order=False)]


def check_strict(path: Path) -> list[tuple[str, int, int, int, bytes]]:
    """What ``mcap doctor --strict-message-order`` checks of the order, and one schema per topic."""
    msgs = file_order(path)
    times = np.array([m[2] for m in msgs], dtype=np.uint64)
    assert len(msgs) and bool(np.all(times[1:] >= times[:-1])), "log times go backwards in the file"
    schemas: dict[str, set[int]] = {}
    for topic, sid, *_ in msgs:
        schemas.setdefault(topic, set()).add(sid)
    assert {t: s for t, s in schemas.items() if len(s) > 1} == {}
    return msgs


@pytest.mark.parametrize("name", ["humanoid_stand", "earthquake_fast"])
def test_a_cli_run_is_in_log_time_order_with_wall_clock_times(tmp_path, name):
    path = tmp_path / f"{name}.mcap"
    before = time.time_ns()
    result = CliRunner().invoke(app, ["run", str(SCENARIOS / f"{name}.yaml"), "--log", str(path), "-q"])
    assert result.exit_code in (0, 1), result.output
    msgs = check_strict(path)
    info = read_index(path).info
    assert before <= info.time_origin_ns <= time.time_ns()  # the run's wall-clock start, not 1970
    for _topic, _sid, log_time, publish_time, _data in msgs:
        assert log_time == info.time_origin_ns + publish_time  # the simulated time stays derivable
    bus = [m for m in msgs if m[0] == "/bus" or m[0].startswith("/bus/layout")]  # earthquake_fast adds a module
    assert [m[3] for m in bus] == [k * DT for k in range(len(bus))] and len(bus) > 1000
    events = [(Log.FromString(m[4]), m[2]) for m in msgs if m[0] == "/events"]
    assert events and all(e.timestamp.ToNanoseconds() == t for e, t in events)
    for log, _t in events:
        body = json.loads(log.message)  # the whole event, as JSON
        assert body["kind"] == log.name and {"seq", "tick", "time", "epoch", "source", "detail"} <= set(body)
    assert any(e.name == "run_end" and e.level == Log.INFO for e, _t in events)


def test_layouts_decimated_poses_and_small_chunks_stay_in_order(tmp_path):
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    McapLogger(tmp_path / "run.mcap", decimate=3, batch=7, chunk_bytes=3000).attach(world, sc)
    world.tick(40)
    world.add_module(Sine("wave", frequency=2.0))
    world.set("wave.amplitude", 2.0)
    world.tick(40)
    world.add_module(Noise("noise", n=2))
    world.tick(40)
    world.close()
    msgs = check_strict(tmp_path / "run.mcap")
    topics = {m[0] for m in msgs}
    assert {"/bus", "/bus/layout2", "/bus/layout3", "/tf", "/scene", "/events"} <= topics
    by_topic = {t: [m[3] // DT for m in msgs if m[0] == t] for t in ("/bus", "/bus/layout2", "/bus/layout3", "/tf")}
    assert by_topic["/bus"] + by_topic["/bus/layout2"] + by_topic["/bus/layout3"] == list(range(121))
    assert by_topic["/tf"] == list(range(0, 121, 3))
    index = read_index(tmp_path / "run.mcap")
    assert index.ordered and index.report.chunks > 5
    kinds = [e["kind"] for e in index.events]
    assert kinds.count("layout") == 3 and kinds.count("module_added") == 2 and "param" in kinds


def test_rollbacks_and_a_branch_imagined_from_the_past_are_put_in_order_on_close(tmp_path):
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    logger = McapLogger(tmp_path / "run.mcap", window=16, batch=8).attach(world, sc)
    world.tick(60)
    world.backtick(10)                       # within the window
    world.tick(30)
    world.backtick(40)                       # reaches ticks already written
    world.tick(20)
    world.imagine("past", 5, {"aa.pos": np.zeros((10, 3))})  # ticks 6..15, long written
    world.close()
    assert logger.stats["out_of_order"] > 0  # written out of order, then rewritten
    check_strict(tmp_path / "run.mcap")
    result = verify(tmp_path / "run.mcap")   # the order the ticks were produced in is still known
    assert result.ok and result.epochs == 2, result.divergence
