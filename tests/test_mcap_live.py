"""The live view: a real foxglove-sdk WebSocket server on loopback, read by a minimal client speaking
the Foxglove WebSocket protocol (subscribe, then binary message frames), and by the ``websockets``
package's client: a client that connects late still gets the scene and the state, and the view sends
every tick or every n-th, as asked."""

from __future__ import annotations

import base64
import json
import os
import select
import socket
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.observers import WorldView
from dynabrain.orchestrator.logs.live import LiveView
from dynabrain.orchestrator.logs.schema import BusCodec, FieldNumbers
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"


class Client:
    """Just enough WebSocket (RFC 6455) for the Foxglove protocol: text frames out, any frame in."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        assert head.startswith(b"HTTP/1.1 101"), head

    def _exact(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            part = self.sock.recv(n - len(out))
            assert part, "the server closed the connection"
            out += part
        return out

    def read(self) -> tuple[int, bytes]:
        b0, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._exact(8))[0]
        return b0 & 0x0F, self._exact(n)

    def send(self, obj: dict) -> None:
        data = json.dumps(obj).encode()
        mask = os.urandom(4)
        head = bytes([0x81]) + (bytes([0x80 | len(data)]) if len(data) < 126 else
                                bytes([0x80 | 126]) + struct.pack(">H", len(data)))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))


def test_live_view_serves_the_bus_and_poses_over_websocket():
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    live = LiveView(port=0, max_rate_hz=0).attach(world)
    try:
        client = Client(live.port)
        channels: dict[str, dict] = {}
        while not {"/bus", "/tf", "/scene", "/events"} <= set(channels):
            opcode, data = client.read()
            msg = json.loads(data) if opcode == 1 else {}
            if msg.get("op") == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
        assert channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
        assert channels["/bus"]["schemaName"] == "dynabrain.layout1.Bus" and channels["/bus"]["encoding"] == "protobuf"
        client.send({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channels["/bus"]["id"]},
                                                          {"id": 2, "channelId": channels["/tf"]["id"]}]})
        codec = BusCodec.from_view(WorldView(world).signal_slots(), world.snapshot().bus.size, FieldNumbers(), 1)
        seen, got = {world.tick_count: world.snapshot().bus}, {1: [], 2: []}  # the latest state comes at once
        while not got[1]:  # the subscription is live once a message arrives
            world.tick()
            seen[world.tick_count] = world.snapshot().bus
            _read_until(client, got, lambda: got[1], timeout=0.05)
        for _ in range(3):
            world.tick()
            seen[world.tick_count] = world.snapshot().bus
        last = live.origin_ns + world.tick_count * 2_000_000  # log time: the wall-clock start + simulated time
        assert _read_until(client, got, lambda: got[1][-1][0] == last and got[2][-1][0] == last, timeout=10)
        for t_ns, payload in got[1]:
            rows, ticks, _epochs = codec.decode(np.frombuffer(payload, dtype=np.uint8))
            assert live.origin_ns + ticks[0] * 2_000_000 == t_ns and rows[0].tobytes() == seen[int(ticks[0])].tobytes()
        assert len(got[1]) >= 4
        tf = FrameTransforms.FromString(got[2][-1][1])
        aa = next(t for t in tf.transforms if t.child_frame_id == "aa")
        assert aa.translation.z == world.get("aa.pos")[2]
    finally:
        world.close()
    assert live.server is None  # closing the world stops the server


def _read_until(client: Client, got: dict, done, timeout: float) -> bool:
    """Read message frames (subscription id -> [(time, payload)]) until ``done()`` or ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not done():
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([client.sock], [], [], left)[0]:
            return False
        opcode, data = client.read()
        if opcode == 2 and data[0] == 0x01:
            sub, t_ns = struct.unpack_from("<IQ", data, 1)
            got[sub].append((t_ns, data[13:]))
    return True


def test_live_view_serves_loopback_only():
    with pytest.raises(DynabrainError, match="loopback only"):
        LiveView(host="0.0.0.0")


def test_run_live_prints_where_it_serves(monkeypatch):
    from typer.testing import CliRunner

    from dynabrain.orchestrator.cli.main import app

    monkeypatch.setenv("DYNABRAIN_LIVE_PORT", "0")
    result = CliRunner().invoke(app, ["run", str(SCENARIOS / "two_cubes.yaml"), "--live", "--no-realtime",
                                      "--live-rate", "50", "-q"])
    assert result.exit_code == 0, result.output
    assert "live view: ws://127.0.0.1:" in result.output and "50 Hz of simulated time" in result.output


@pytest.mark.parametrize(("args", "paced"), [(["--live"], True), (["--live", "--no-realtime"], False),
                                             ([], None), (["--realtime"], True)])
def test_live_paces_the_run_at_real_time_unless_told_otherwise(monkeypatch, args, paced):
    from typer.testing import CliRunner

    from dynabrain.orchestrator.cli import main

    asked = []

    def runner(sc, world, *, progress=None, realtime=None):
        asked.append(realtime)
        return real(sc, world, progress=progress, realtime=False)

    real = main.run_scenario
    monkeypatch.setattr(main, "run_scenario", runner)
    monkeypatch.setenv("DYNABRAIN_LIVE_PORT", "0")
    result = CliRunner().invoke(main.app, ["run", str(SCENARIOS / "two_cubes.yaml"), *args, "-q"])
    assert result.exit_code == 0, result.output
    assert asked == [paced]  # None: as the scenario says (two_cubes: not paced)


class Late:
    """A Foxglove WebSocket client made with the ``websockets`` package (its sync client)."""

    def __init__(self, port: int):
        from websockets.sync.client import connect

        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=10, legacy=True)
        self.channels: dict[str, dict] = {}
        self.subs: dict[int, str] = {}
        self.got: dict[str, list[tuple[int, bytes]]] = {}

    def advertised(self, topics: set[str]) -> None:
        while not topics <= set(self.channels):
            msg = self.ws.recv(timeout=10)
            if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
                self.channels.update({c["topic"]: c for c in json.loads(msg)["channels"]})

    def subscribe(self, topics: list[str]) -> None:
        subs = [{"id": i + 1, "channelId": self.channels[t]["id"]} for i, t in enumerate(topics)]
        self.subs = {s["id"]: t for s, t in zip(subs, topics, strict=True)}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def read(self, done, timeout: float = 10) -> bool:
        """Message frames (topic -> [(log time, payload)]) until ``done()`` or ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while not done():
            try:
                msg = self.ws.recv(timeout=max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                return False
            if isinstance(msg, bytes) and msg[0] == 0x01:
                sub, t_ns = struct.unpack_from("<IQ", msg, 1)
                self.got.setdefault(self.subs[sub], []).append((t_ns, msg[13:]))
        return True


def test_a_client_that_connects_late_gets_the_scene_and_the_state():
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    world = load_scenario(SCENARIOS / "two_cubes.yaml").build()
    live = LiveView(port=0).attach(world)
    try:
        world.tick(50)
        world.set("core.friction", 0.5)
        world.tick(25)  # the run is over before anyone looks: nothing ticks any more
        client = Late(live.port)
        assert client.ws.subprotocol == "foxglove.sdk.v1"
        topics = ["/scene", "/bus", "/tf", "/events"]
        client.advertised(set(topics))
        client.subscribe(topics)
        assert client.read(lambda: set(topics) <= set(client.got))
        t_end = live.origin_ns + 75 * 2_000_000
        (t_bus, bus), = client.got["/bus"]
        codec = BusCodec.from_view(WorldView(world).signal_slots(), world.snapshot().bus.size, FieldNumbers(), 1)
        rows, ticks, _epochs = codec.decode(np.frombuffer(bus, dtype=np.uint8))
        assert ticks[0] == 75 and t_bus == t_end and rows[0].tobytes() == world.snapshot().bus.tobytes()
        (t_tf, tf), = client.got["/tf"]
        aa = next(t for t in FrameTransforms.FromString(tf).transforms if t.child_frame_id == "aa")
        assert t_tf == t_end and aa.translation.z == world.get("aa.pos")[2]
        scene = SceneUpdate.FromString(client.got["/scene"][0][1])
        assert {e.id for e in scene.entities} >= {"aa", "bb"}
        kinds = lambda: [Log.FromString(m).name for _t, m in client.got["/events"]]  # noqa: E731
        assert client.read(lambda: "param" in kinds()) and kinds()[0] == "run_start"  # the kept events, in order
    finally:
        world.close()


@pytest.mark.parametrize("every", [1, 5])
def test_the_view_sends_every_tick_or_every_nth(every):
    world = load_scenario(SCENARIOS / "two_cubes.yaml").build()
    live = LiveView(port=0, every=every).attach(world)
    try:
        client = Late(live.port)
        client.advertised({"/bus"})
        client.subscribe(["/bus"])
        assert client.read(lambda: client.got.get("/bus"))  # the latest state, at once
        world.tick(100)
        last = live.origin_ns + 100 * 2_000_000
        assert client.read(lambda: client.got["/bus"][-1][0] == last)
        ticks = [(t - live.origin_ns) // 2_000_000 for t, _m in client.got["/bus"]]
        assert ticks == [0, *range(every, 101, every)] and live.sent == len(ticks)
    finally:
        world.close()
