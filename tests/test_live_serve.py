"""The Foxglove view beyond `dynabrain run`: a served world (`serve --live`) seen by a real WebSocket client
while a remote brain drives it over Zenoh, a recorded run played to one (`replay --live`, also beside
``--publish``), a port in use refused naming the port and the option with the world and the log untouched,
and the WebSocket subprotocols foxglove-sdk's server accepts (so that an SDK which starts taking
``foxglove.websocket.v1`` is noticed)."""

from __future__ import annotations

import contextlib
import os
import socket
import threading

import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from test_mcap_live import Late
from typer.testing import CliRunner
from websockets.exceptions import ConnectionClosed

from dynabrain.bridge import BrainClient
from dynabrain.bridge.server import BridgeServer, ServeOptions
from dynabrain.bridge.testing import wait_for
from dynabrain.bridge.zenoh_io import Settings, free_port
from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.logs.live import SUBPROTOCOLS, LiveOptions, LiveView
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import iter_bus, read_index
from dynabrain.orchestrator.logs.replay import LogView
from dynabrain.orchestrator.logs.schema import TOPIC_BUS
from dynabrain.orchestrator.scenario import load_world
from dynabrain.orchestrator.scenario.model import load_scenario

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
DT = 2_000_000


def ticks_of(client: Late, topic: str, origin_ns: int) -> list[int]:
    return [(t - origin_ns) // DT for t, _m in client.got.get(topic, [])]


def test_a_served_world_is_seen_in_foxglove_while_a_remote_brain_drives_it():
    world = load_world(ARM)
    server = BridgeServer(world, Settings(listen=["tcp/127.0.0.1:0"]), ServeOptions(live=LiveOptions(port=0)))
    try:
        server.open()
        live = server.live
        client = Late(live.port)
        topics = ["/bus", "/tf", "/scene", "/events"]
        client.advertised(set(topics))
        client.subscribe(topics)
        assert client.read(lambda: {"/bus", "/tf", "/scene"} <= set(client.got))  # the latest state, at once
        with BrainClient("arm", connect=server.endpoints, timeout=20) as brain:
            brain.set("servo.target", [0.4, 0.7, -1.0])
            brain.tick(30)
        assert client.read(lambda: ticks_of(client, "/bus", live.origin_ns)[-1:] == [30] == [
            (t - live.origin_ns) // DT for t, _m in client.got["/tf"][-1:]])
        assert ticks_of(client, "/bus", live.origin_ns) == list(range(31))  # every tick the brain made
        tf = FrameTransforms.FromString(client.got["/tf"][-1][1])
        pose = {t.child_frame_id: t.translation.z for t in tf.transforms}
        assert pose and all(pose[b] == world.get(f"core.{b}.pos")[2] for b in pose)
        assert client.read(lambda: any(b'"param"' in m or b'"set"' in m for _t, m in client.got.get("/events", [])))
    finally:
        server.close()
        world.close()
    assert server.live is None and live.server is None


def busy_port() -> socket.socket:
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen()
    return sock


def test_a_port_in_use_is_refused_naming_it_and_the_world_is_untouched():
    world = load_world(ARM)
    with busy_port() as sock:
        port = sock.getsockname()[1]
        server = BridgeServer(world, Settings(listen=["tcp/127.0.0.1:0"]),
                              ServeOptions(live=LiveOptions(port=port, port_option="--live-port")))
        try:
            with pytest.raises(DynabrainError, match=f"127.0.0.1:{port} \\(--live-port {port}\\).*in use"):
                server.open()
            assert server.session is None and server.live is None  # nothing served over Zenoh either
            assert world.tick_count == 0 and not any(isinstance(o, LiveView) for o in world.observers)
            world.tick(3)
        finally:
            server.close()
            world.close()
        # the default port (none asked for) moves to a free one instead
        view = LiveView(port=port).attach(load_world(ARM))
        assert view.port != port
        view.close()


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """60 ticks of the arm, with a backtick of 20 (the discarded ticks stay off the view)."""
    path = tmp_path_factory.mktemp("live") / "arm.mcap"
    sc = load_scenario(ARM)
    world = sc.build()
    McapLogger(path).attach(world, sc)
    world.set("servo.target", [0.4, 0.7, -1.0])
    world.tick(40)
    world.backtick(20)
    world.tick(40)
    world.close()
    return path


def run_rows(path) -> dict[int, np.ndarray]:
    index = read_index(path)
    final = index.final(TOPIC_BUS)
    return {tick: row for _c, _e, tick, row, pos, _t in iter_bus(path, index) if pos in final}


def test_a_replayed_log_is_played_to_foxglove(recording):
    index = read_index(recording)
    origin = int(index.info.time_origin_ns)
    view = LogView(recording, port=0, speed=4.0).start()
    try:
        client = Late(view.port)
        client.advertised({"/bus", "/tf", "/scene", "/events"})
        assert not [t for t in client.channels if t.startswith("/discarded")]
        client.subscribe(["/bus", "/tf", "/events"])
        result = view.play(wait_s=10)
        rows = run_rows(recording)
        assert client.read(lambda: len(client.got.get("/bus", [])) == len(rows))
        assert result.messages >= 2 * len(rows)
        assert ticks_of(client, "/bus", origin) == sorted(rows) == list(range(61))  # the run, not what was discarded
        codec = index.bus_codec(next(c for c, ch in index.channels.items() if ch.topic == TOPIC_BUS))
        for t_ns, payload in client.got["/bus"]:
            got, ticks, _e = codec.decode(np.frombuffer(payload, dtype=np.uint8))
            assert origin + ticks[0] * DT == t_ns and got[0].tobytes() == rows[int(ticks[0])].tobytes()
        assert client.read(lambda: any(b"rollback" in m for _t, m in client.got.get("/events", [])))
    finally:
        view.close()


def test_replay_live_on_the_command_line(recording):
    port = free_port()
    result: dict = {}
    thread = threading.Thread(target=lambda: result.update(r=CliRunner().invoke(
        app, ["replay", str(recording), "--live", "--live-port", str(port)])))
    thread.start()
    try:
        client = wait_for(lambda: _connect(port), timeout=20, what="the replay's live view")
        client.advertised({"/bus"})
        client.subscribe(["/bus"])
        with contextlib.suppress(ConnectionClosed):  # the command ends once it has played the log
            client.read(lambda: len(client.got.get("/bus", [])) == 61)
    finally:
        thread.join(30)
    ticks = ticks_of(client, "/bus", int(read_index(recording).info.time_origin_ns))
    assert ticks and ticks == sorted(set(ticks)) and set(ticks) <= set(range(61))  # the run's ticks, in order
    assert result["r"].exit_code == 0, result["r"].output
    assert f"live view: ws://127.0.0.1:{port}" in result["r"].output and "played" in result["r"].output


def _connect(port: int) -> Late | None:
    try:
        return Late(port)
    except OSError:
        return None


def test_replay_publish_live_on_a_port_in_use_is_a_clear_error(recording):
    before = recording.read_bytes()
    with busy_port() as sock:
        port = sock.getsockname()[1]
        result = CliRunner().invoke(app, ["replay", str(recording), "--publish", "--live", "--live-port", str(port)])
    assert result.exit_code == 2, result.output
    assert f"--live-port {port}" in result.output and "in use" in result.output
    assert "replaying world" not in result.output  # nothing was published
    assert recording.read_bytes() == before


def test_the_subprotocols_the_sdk_accepts():
    """foxglove-sdk (0.30) accepts its own ``foxglove.sdk.v1`` (and ``.v1.1``) and refuses the older
    ``foxglove.websocket.v1`` alone with HTTP 400, and start_server has no option to add it; the Foxglove
    app offers both names, so it connects. A change of the SDK shows here."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    view = LiveView(port=0).attach(load_world(ARM))
    accepted, refused = [], []
    try:
        for offer in ("foxglove.websocket.v1", *SUBPROTOCOLS):
            try:
                with connect(view.url, subprotocols=[offer], open_timeout=10) as ws:
                    accepted.append(ws.subprotocol)
            except InvalidStatus as exc:
                refused.append((offer, exc.response.status_code))
        with connect(view.url, subprotocols=["foxglove.websocket.v1", "foxglove.sdk.v1"], open_timeout=10) as ws:
            assert ws.subprotocol == "foxglove.sdk.v1"  # what the Foxglove app offers
    finally:
        view.close()
    assert accepted == list(SUBPROTOCOLS) and refused == [("foxglove.websocket.v1", 400)]


def test_run_live_on_a_port_in_use_stops_before_anything_is_recorded(tmp_path):
    log = tmp_path / "run.mcap"
    with busy_port() as sock:
        port = sock.getsockname()[1]
        result = CliRunner().invoke(app, ["run", "two_cubes", "--live", "--live-port", str(port), "--log", str(log),
                                          "--no-realtime", "-q"])
    assert isinstance(result.exception, DynabrainError), result.output  # `dynabrain` prints it and exits 2
    assert f"--live-port {port}" in str(result.exception) and not log.exists()
