"""Late live clients (issue 29): a Foxglove client (the ``websockets`` package's, speaking the SDK's
protocol) that connects after the run is over gets, besides the latest state, the run's start, its
expectation results and its end on ``/events``, in the order they were sent, however many events came
between; through `dynabrain run --live`'s outputs, and from a played log."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.Log_pb2 import Log
from test_mcap_live import Late

from dynabrain.orchestrator.cli.log import attach_run_outputs
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.observers import WorldView
from dynabrain.orchestrator.logs.live import LiveView
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.replay import LogView
from dynabrain.orchestrator.logs.schema import BusCodec, FieldNumbers
from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
DT = 2_000_000


def events_of(client: Late) -> list[dict]:
    """The events a client got, as the JSON each ``foxglove.Log`` holds, with its log time."""
    out = []
    for t_ns, data in client.got.get("/events", []):
        log = Log.FromString(data)
        event = json.loads(log.message)
        assert log.name == event["kind"]
        out.append({**event, "log_time": t_ns})
    return out


def late_client(port: int, topics: list[str], done) -> Late:
    client = Late(port)
    client.advertised(set(topics))
    client.subscribe(topics)
    assert client.read(lambda: done(client)), f"got only {sorted(client.got)}"
    return client


def test_a_late_client_gets_the_runs_start_results_and_end_however_many_events_came_between():
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    live = LiveView(port=0, keep_events=3).attach(world, sc)
    try:
        world.tick(10)
        for k in range(20):  # more events than the view keeps of the recent ones
            world.set("core.friction", 0.5 + k / 100)
        result = run_scenario(sc, world)
        live.log_result(result)
        ends = lambda c: any(e["kind"] == "run_end" for e in events_of(c)) and "/bus" in c.got  # noqa: E731
        client = late_client(live.port, ["/events", "/bus"], ends)
        events = events_of(client)
        kinds = [e["kind"] for e in events]
        n = len(result.expectations)
        assert kinds == ["run_start", *["expect"] * n, "run_end"]  # the recent events are the results
        assert [e["seq"] for e in events] == sorted(e["seq"] for e in events)
        start, end = events[0], events[-1]
        assert start["detail"]["scenario_name"] == "two_cubes" and start["detail"]["dt_ns"] == DT
        assert start["detail"]["start_tick"] == 0 and start["detail"]["time_origin_ns"] == live.origin_ns
        assert start["log_time"] == live.origin_ns and end["log_time"] == live.origin_ns + result.ticks * DT
        assert end["detail"]["ok"] and end["detail"]["ticks"] == result.ticks == 2500
        assert [e["detail"]["name"] for e in events[1:-1]] == [x.label for x in result.expectations]
        assert all(e["detail"]["passed"] for e in events[1:-1])
        (t_bus, bus), = client.got["/bus"]  # and the latest state, at the run's last tick
        codec = BusCodec.from_view(WorldView(world).signal_slots(), world.snapshot().bus.size, FieldNumbers(), 1)
        rows, ticks, _e = codec.decode(np.frombuffer(bus, dtype=np.uint8))
        assert ticks[0] == 2500 and t_bus == end["log_time"] and rows[0].tobytes() == world.snapshot().bus.tobytes()
    finally:
        world.close()
    with pytest.raises(DynabrainError, match="not serving"):
        live.log_result(result)


def test_recent_events_come_between_the_start_and_the_results_in_order():
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    live = LiveView(port=0, keep_events=5).attach(world, sc)
    try:
        for k in range(8):
            world.set("core.friction", 0.5 + k / 100)
        world.tick(3)
        ends = lambda c: len(events_of(c)) == 6  # noqa: E731
        client = late_client(live.port, ["/events"], ends)
        events = events_of(client)
        assert [e["kind"] for e in events] == ["run_start", *["param"] * 5]  # the start, then the 5 latest
        assert [e["detail"]["value"] for e in events[1:]] == pytest.approx([0.53, 0.54, 0.55, 0.56, 0.57])
    finally:
        world.close()


def test_dynabrain_run_live_sends_the_results_to_a_client_that_connects_after_the_run(monkeypatch):
    """The outputs `dynabrain run --live` attaches: the view starts with the scenario and gets the results."""
    from rich.console import Console

    monkeypatch.setenv("DYNABRAIN_LIVE_PORT", "0")
    sc = load_scenario(SCENARIOS / "bounce.yaml")
    world = sc.build()
    outputs = attach_run_outputs(world, sc, log=None, live=True, console=Console(quiet=True))
    try:
        result = run_scenario(sc, world, realtime=False)
        outputs.finish(result)  # stdin is no terminal here: it does not wait
        ends = lambda c: any(e["kind"] == "run_end" for e in events_of(c))  # noqa: E731
        events = events_of(late_client(outputs.live.port, ["/events"], ends))
        kinds = [e["kind"] for e in events]
        assert kinds[0] == "run_start" and kinds[-1] == "run_end" and events[0]["detail"]["scenario_name"] == "bounce"
        assert kinds.count("expect") == len(result.expectations) >= 1
        assert events[-1]["detail"]["ok"] == result.ok
    finally:
        world.close()


def test_a_late_client_of_a_played_log_gets_its_results(tmp_path):
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    logger = McapLogger(tmp_path / "run.mcap").attach(world, sc)
    result = run_scenario(sc, world)
    logger.log_result(result)
    world.close()
    view = LogView(tmp_path / "run.mcap", port=0, speed=float("inf")).start()
    try:
        view.play(wait_s=0)  # played to nobody: the client comes after
        ends = lambda c: any(e["kind"] == "run_end" for e in events_of(c))  # noqa: E731
        events = events_of(late_client(view.port, ["/events"], ends))
        kinds = [e["kind"] for e in events]
        assert kinds.count("expect") == len(result.expectations) and kinds[-1] == "run_end"
    finally:
        view.close()
