"""Live view: a running world served to the Foxglove app over its WebSocket protocol, on loopback.

The same channels as a log (`logs.schema`): ``/bus`` (``/bus/layout<k>`` after modules come or go),
``/tf``, ``/scene``, ``/events`` (``foxglove.Log``), encoded the same way, with the same times (log
time: the wall-clock time at `attach` plus the simulated time since), through foxglove-sdk's server
bound to 127.0.0.1 (port 8765 by default, the app's default; another free port when that one is
taken; 0 asks for any; a port asked for by an option that is taken is an error naming both, `LiveOptions`).
`dynabrain run --live`, ``serve --live`` (`BridgeServer`'s ``options.live``) and ``replay --live``
(`logs.replay.LogView`, a recorded run) share the server part, `FoxgloveServer`.

Subprotocol. foxglove-sdk 0.30.3 (the one installed) accepts ``foxglove.sdk.v1`` and ``foxglove.sdk.v1.1``
only (`SUBPROTOCOLS`): its handshake (``rust/foxglove/src/websocket/handshake.rs``: "If the client requests
subprotocols which don't contain ours, or does not include the expected header, return a 400") refuses a
client that offers only ``foxglove.websocket.v1``, the older name, with HTTP 400 "Missing expected
sec-websocket-protocol header", and ``start_server`` has no option for another name (its parameters: name,
host, port, capabilities, listener, encodings, services, assets, context, session, channel filter, playback
range, backlog, TLS). The Foxglove app offers both names and gets ``foxglove.sdk.v1``.

Rate. The view sends every ``every``-th tick (1, the default: every tick the world makes, at the
world's own rate: 500 messages a second per channel for a 2 ms step), and at once after a rollback or
a new layout; ``max_rate_hz`` caps that further by wall-clock time (0: no cap). `dynabrain run --live`
paces the run at real time (unless ``--no-realtime``) and takes ``--live-rate`` in Hz of simulated
time. Every event is sent.

The run. When the view starts it sends a ``run_start`` event (the world, the scenario, the step, the
seed, the tick and wall-clock time it starts at, the log time of tick 0); `LiveView.log_result` sends the
run's expectation results and its ``run_end`` (`dynabrain run --live` calls it), as a log holds them.

Late clients. The view keeps the latest message of each channel (state, poses, scene), the last
``keep_events`` events, and every event of the run's start, results and end (`schema.RUN_KINDS`), however
many events came between; a client that subscribes to a channel gets them at once (sent to that client
only, the events in the order they were sent), so a client that connects after the scene was drawn, or
after the run is over, still sees it, and how it went. A played log (`logs.replay.LogView`) keeps its
recorded results the same way. The scene is sent when the view starts, after each `make` and rollback, and
to each new subscriber.
"""

from __future__ import annotations

import datetime
import json
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, NamedTuple

import foxglove
import numpy as np
from foxglove.websocket import ServerListener
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.message import DecodeError

from ..kernel.errors import DynabrainError
from ..kernel.observers import Observer, WorldEvent, WorldView
from .scene import SceneDrawing
from .schema import (
    RUN_KINDS,
    TOPIC_EVENTS,
    TOPIC_SCENE,
    TOPIC_TF,
    BusCodec,
    FieldNumbers,
    PoseCodec,
    bus_topic,
    event_bytes,
    event_level,
    foxglove_descriptor,
    log_message,
    pose_columns,
    result_events,
)

_log = logging.getLogger("dynabrain.mcap")
DEFAULT_PORT = 8765
KEEP_EVENTS = 100
"""Events a client that subscribes late still gets (the latest ones)."""
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.sdk.v1.1")
"""The WebSocket subprotocols the server accepts (foxglove-sdk's own; see the module docstring), checked by
tests/test_live_serve.py, so that an SDK that starts accepting ``foxglove.websocket.v1`` is noticed."""


@dataclass(frozen=True)
class LiveOptions:
    """Where and how often a live view serves: ``dynabrain run --live``, ``serve --live``, ``replay --live``.

    ``port``: 0 asks for any free port; ``port_option``: the option or variable that asked for this port
    (``--live-port``, ``DYNABRAIN_LIVE_PORT``): a port in use is then an error naming it; without one (the
    default port) the view takes another free port and says so. ``every``: send every that many ticks."""

    port: int = DEFAULT_PORT
    port_option: str | None = None
    every: int = 1
    host: str = "127.0.0.1"

    def start(self, world: Any, scenario: Any = None) -> LiveView:
        """A `LiveView` of ``world`` (built from ``scenario``, when there is one), serving (a port in use raises
        `DynabrainError`; the world is untouched)."""
        return LiveView(host=self.host, port=self.port, every=self.every,
                        port_option=self.port_option).attach(world, scenario)


def check_host(host: str) -> str:
    if host not in ("127.0.0.1", "localhost", "::1"):
        raise DynabrainError(f"the live view serves on loopback only, not on {host!r}")
    return host


class _Sent(NamedTuple):
    """An event sent: ``n`` counts the events sent, so a late client gets the kept ones in order."""

    n: int
    data: bytes
    t_ns: int


class FoxgloveServer:
    """foxglove-sdk's WebSocket server with the channels of one view, which keeps the latest message of each
    channel (of the events channel: the recent ones, and those of the run's start, results and end) and
    sends them to a client that subscribes late. Used by `LiveView` (a world) and `logs.replay.LogView` (a
    recorded run)."""

    def __init__(self, name: str = "dynabrain", keep_events: int = KEEP_EVENTS):
        self.name = name
        self.ctx: Any = foxglove.Context()
        self.server: Any = None
        self.events: Any = None
        """The channel whose recent messages (not only the latest) a late subscriber gets."""
        self.subscribed = threading.Event()
        """Set once a client has subscribed to a channel."""
        self._lock = threading.Lock()  # the latest messages, and sending them
        self._latest: dict[int, tuple[bytes, int]] = {}  # channel id -> its latest message and log time
        self._recent: deque[_Sent] = deque(maxlen=keep_events)
        self._run: list[_Sent] = []  # the events of the run's start, results and end: all of them
        self._sent_events = 0
        self._events_json = False  # a played log's events may be JSON (``dynabrain.Event``), not foxglove.Log
        self._channels: dict[int, Any] = {}

    def channel(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes,
                message_encoding: str, metadata: dict[str, str] | None = None, events: bool = False) -> Any:
        schema = foxglove.Schema(name=schema_name, encoding=schema_encoding, data=schema_data) if schema_name else None
        ch = foxglove.Channel(topic, schema=schema, message_encoding=message_encoding, context=self.ctx,
                              metadata=metadata)
        self._channels[ch.id()] = ch
        if events:
            self.events, self._events_json = ch, message_encoding == "json"
        return ch

    def proto_channel(self, topic: str, message_class: type, events: bool = False) -> Any:
        return self.channel(topic, message_class.DESCRIPTOR.full_name, "protobuf", foxglove_descriptor(message_class),
                            "protobuf", events=events)

    def drop(self, channel: Any) -> None:
        """Close a channel (its topic goes away for clients)."""
        with self._lock:
            self._latest.pop(channel.id(), None)
            self._channels.pop(channel.id(), None)
        channel.close()

    def send(self, channel: Any, data: bytes, t_ns: int, kind: str | None = None) -> None:
        """Send a message to every subscriber and keep it for late ones. ``kind``: an event's kind (read
        from the message when not given), so that the run's start, results and end are kept."""
        with self._lock:
            if channel is self.events:
                self._sent_events += 1
                sent = _Sent(self._sent_events, data, t_ns)
                self._recent.append(sent)
                if (kind or self._event_kind(data)) in RUN_KINDS:
                    self._run.append(sent)
            else:
                self._latest[channel.id()] = (data, t_ns)
            channel.log(data, log_time=t_ns)

    def _event_kind(self, data: bytes) -> str | None:
        """The kind of an event message: a foxglove.Log's name (the JSON's ``kind`` in older logs)."""
        try:
            return json.loads(data).get("kind") if self._events_json else Log.FromString(data).name
        except (ValueError, AttributeError, DecodeError):
            return None

    def start(self, host: str, port: int, port_option: str | None = None) -> Any:
        """Start serving on ``host:port`` (see `LiveOptions` for a port in use)."""
        listener = _Latest(self)
        try:
            self.server = foxglove.start_server(name=self.name, host=host, port=port, context=self.ctx,
                                                server_listener=listener)
        except RuntimeError as exc:
            taken = "bind" in str(exc).lower()
            if port == 0 or not taken:
                raise DynabrainError(f"the live view cannot start its WebSocket server: {exc}") from None
            if port_option is not None:
                raise DynabrainError(f"the live view cannot listen on {host}:{port} ({port_option} {port}): the port "
                                     "is in use; choose another (0: any free port)") from None
            _log.warning("port %s is taken; the live view uses another", port)
            self.server = foxglove.start_server(name=self.name, host=host, port=0, context=self.ctx,
                                                server_listener=listener)
        return self.server

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    def catch_up(self, client_id: int, channel_id: int) -> None:
        """Send a client that subscribed to a channel its latest message (the recent ones: events)."""
        with self._lock:
            channel = self._channels.get(channel_id)
            if channel is None:
                return
            if channel is self.events:  # the run's events and the recent ones, once each, in order
                for sent in sorted({s.n: s for s in (*self._run, *self._recent)}.values()):
                    channel.log(sent.data, log_time=sent.t_ns, sink_id=client_id)
                return
            latest = self._latest.get(channel_id)
            if latest is not None:
                channel.log(latest[0], log_time=latest[1], sink_id=client_id)


class LiveView(Observer):
    """Serves a world to Foxglove (see the module docstring). ``attach`` starts the server.

    ``every``: send every that many ticks; ``max_rate_hz``: at most that many times per wall-clock second
    (0: no cap); ``scene_every_s``: send the scene again that often (None: only when it changes and to new
    subscribers); ``keep_events``: events kept for late subscribers; ``port_option``: see `LiveOptions`.
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, every: int = 1,
                 max_rate_hz: float = 0.0, scene_every_s: float | None = None, keep_events: int = KEEP_EVENTS,
                 name: str = "dynabrain", port_option: str | None = None):
        check_host(host)
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise DynabrainError(f"the live view's every must be a whole number of ticks >= 1, got {every!r}")
        self.host, self.requested_port, self.name, self.every = host, port, name, every
        self.port_option = port_option
        self.min_interval = 1.0 / max_rate_hz if max_rate_hz > 0 else 0.0
        self.scene_every_s = scene_every_s
        self.origin_ns = 0
        """The log time of tick 0 (as in a log: the wall-clock time at `attach`, less that tick's simulated time)."""
        self.sent = 0
        """Ticks sent."""
        self._fox = FoxgloveServer(name, keep_events)
        self._numbers = FieldNumbers()
        self._codecs: dict[tuple, BusCodec] = {}
        self._codec: BusCodec | None = None
        self._bus: Any = None
        self._dirty = True
        self._last = -1e9
        self._last_scene = -1e9
        self._scene_due = True
        self._epoch = 0
        self._seq = 0
        self._poses: PoseCodec | None = None
        self._scene: SceneDrawing | None = None
        self._tf: Any = None
        self._scene_ch: Any = None
        self._events: Any = None
        self._world: Any = None

    @property
    def server(self) -> Any:
        """foxglove-sdk's server (None once closed)."""
        return self._fox.server

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def attach(self, world: Any, scenario: Any = None) -> LiveView:
        """Start serving ``world`` (built from ``scenario``, when there is one: its ``run_start`` names it); a
        port in use raises `DynabrainError` before the view observes it."""
        with world.lock():
            fox = self._fox
            self._world, self._dt = world, world.dt_ns
            view = WorldView(world)
            wall_ns = time.time_ns()
            self.origin_ns = wall_ns - view.tick * self._dt
            self._events = fox.proto_channel(TOPIC_EVENTS, Log, events=True)
            self._send_event("run_start", view.tick, self._start_detail(world, scenario, wall_ns), "log")
            if view.core is not None:
                self._poses = PoseCodec(view.core.bodies())
                self._scene = SceneDrawing(view.core)
                self._tf = fox.proto_channel(TOPIC_TF, FrameTransforms)
                self._scene_ch = fox.proto_channel(TOPIC_SCENE, SceneUpdate)
            self._publish(view)
            fox.start(self.host, self.requested_port, self.port_option)
            world.observe(self)
        return self

    # -- observer hooks -------------------------------------------------------------------------------
    def on_tick(self, view: WorldView) -> None:
        if view.tick % self.every:
            return
        if self.min_interval:
            now = time.monotonic()
            if now - self._last < self.min_interval:
                return
            self._last = now
        self._publish(view)

    def on_rollback(self, view: WorldView, from_tick: int) -> None:
        self._epoch += 1
        self._dirty = True
        self._send_event("rollback", view.tick, {"from_tick": from_tick, "to_tick": view.tick, "epoch": self._epoch})
        self._scene_due = True
        self._publish(view)

    def on_event(self, view: WorldView, event: WorldEvent) -> None:
        if event.kind in ("module_added", "module_removed"):
            self._dirty = True
        elif event.kind == "make":
            self._scene_due = True
        self._send_event(event.kind, event.tick, event.detail, event.source)

    def on_close(self, view: WorldView) -> None:
        self.close()

    def log_result(self, result: Any) -> None:
        """Send a run's expectation results and its end (a `RunResult`; `dynabrain run --live` calls this), the
        events a log holds for them; a client that connects later still gets them."""
        if self.server is None:
            raise DynabrainError("the live view is not serving (attach it to a world first, and before it closes)")
        with self._world.lock():
            for kind, detail in result_events(result):
                self._send_event(kind, int(result.ticks), detail, "log")

    def _start_detail(self, world: Any, scenario: Any, wall_ns: int) -> dict:
        """What ``run_start`` says: the keys of a log's ``dynabrain`` metadata that a viewer needs (`logs.meta`),
        as plain values."""
        start = datetime.datetime.fromtimestamp(wall_ns / 1e9, datetime.UTC).isoformat(timespec="milliseconds")
        detail = {"world": world.name, "dt_ns": self._dt, "seed": world.seed, "start_tick": world.tick_count,
                  "start_time": start, "time_origin_ns": self.origin_ns}
        if scenario is not None:
            detail.update(scenario_name=scenario.model.name, scenario_path=str(scenario.path),
                          duration_ns=scenario.duration_ns)
        return detail

    def close(self) -> None:
        self._fox.close()

    # -- publishing -----------------------------------------------------------------------------------
    def _publish(self, view: WorldView) -> None:
        bus = view.bus()
        if self._dirty or self._codec is None or bus.size != self._codec.size:
            self._new_layout(view)
        tick = view.tick
        t_ns = self.origin_ns + tick * self._dt
        row = bus[None, :]
        send = self._fox.send
        send(self._bus, self._codec.encode(row, [tick], [self._epoch], self._dt)[0].tobytes(), t_ns)
        if self._poses is not None:
            ext = row
            if self._missing:
                extra = np.concatenate([np.concatenate(view.core.body_pose(b)) for b in self._missing])
                ext = np.concatenate([row, extra[None, :]], axis=1)
            pose = ext[:, self._cols]
            send(self._tf, self._poses.encode(pose[:, :, :3], pose[:, :, 3:], np.array([t_ns]))[0].tobytes(), t_ns)
            now = time.monotonic()
            if self._scene_due or (self.scene_every_s is not None and now - self._last_scene >= self.scene_every_s):
                self._scene_due, self._last_scene = False, now
                send(self._scene_ch, self._scene.encode(t_ns), t_ns)
        self.sent += 1

    def _new_layout(self, view: WorldView) -> None:
        slots, size = view.signal_slots(), view.bus().size
        signature = (*sorted((n, o, tuple(sh), u) for n, (o, sh, u) in slots.items()), size)
        codec = self._codecs.get(signature)
        if codec is None:
            codec = self._codecs[signature] = BusCodec.from_view(slots, size, self._numbers, len(self._codecs) + 1)
        if codec is not self._codec:
            if self._bus is not None:  # one schema per topic: the old layout's topic goes away
                self._fox.drop(self._bus)
            self._bus = self._fox.channel(bus_topic(codec.key), codec.schema_name, "protobuf", codec.descriptor(),
                                          "protobuf", codec.metadata())
            self._codec = codec
        if self._poses is not None:
            self._cols, self._missing = pose_columns(view.core.name, self._poses.bodies, self._codec)
        self._dirty = False

    def _send_event(self, kind: str, tick: int, detail: dict, source: str = "api") -> None:
        self._seq += 1
        body = {"seq": self._seq, "tick": tick, "time": tick * self._dt / 1e9, "epoch": self._epoch, "kind": kind,
                "source": source, "detail": detail}
        t_ns = self.origin_ns + tick * self._dt
        self._fox.send(self._events, log_message(t_ns, event_level(kind, detail), event_bytes(body).decode(), kind),
                       t_ns, kind)


class _Latest(ServerListener):
    """Tells the server about each subscription; it answers from a thread of its own (the SDK calls this on
    its own thread, where sending is not safe to do under the server's lock)."""

    def __init__(self, fox: FoxgloveServer):
        self.fox = fox

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.fox.subscribed.set()
        threading.Thread(target=self.fox.catch_up, args=(client.id, channel.id), daemon=True,
                         name="dynabrain-live-catch-up").start()
