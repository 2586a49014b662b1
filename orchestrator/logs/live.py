"""Live view: a running world served to the Foxglove app over its WebSocket protocol, on loopback.

The same channels as a log (`logs.schema`): ``/bus`` (``/bus/layout<k>`` after modules come or go),
``/tf``, ``/scene``, ``/events`` (``foxglove.Log``), encoded the same way, with the same times (log
time: the wall-clock time at `attach` plus the simulated time since), through foxglove-sdk's server
bound to 127.0.0.1 (port 8765 by default, the app's default; another free port when that one is
taken; 0 asks for any). The server speaks the ``foxglove.sdk.v1`` subprotocol, the only one
foxglove-sdk accepts (it refuses ``foxglove.websocket.v1``, the older name, with HTTP 400); the
Foxglove app offers both.

Rate. The view sends every ``every``-th tick (1, the default: every tick the world makes, at the
world's own rate: 500 messages a second per channel for a 2 ms step), and at once after a rollback or
a new layout; ``max_rate_hz`` caps that further by wall-clock time (0: no cap). `dynabrain run --live`
paces the run at real time (unless ``--no-realtime``) and takes ``--live-rate`` in Hz of simulated
time. Every event is sent.

Late clients. The view keeps the latest message of each channel (state, poses, scene) and the last
``keep_events`` events; a client that subscribes to a channel gets them at once (sent to that client
only), so a client that connects after the scene was drawn, or after the run is over, still sees it.
The scene is sent when the view starts, after each `make` and rollback, and to each new subscriber.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Any

import foxglove
import numpy as np
from foxglove.websocket import ServerListener
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from ..kernel.errors import DynabrainError
from ..kernel.observers import Observer, WorldEvent, WorldView
from .scene import SceneDrawing
from .schema import (
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
)

_log = logging.getLogger("dynabrain.mcap")
DEFAULT_PORT = 8765
KEEP_EVENTS = 100
"""Events a client that subscribes late still gets (the latest ones)."""


class LiveView(Observer):
    """Serves a world to Foxglove (see the module docstring). ``attach`` starts the server.

    ``every``: send every that many ticks; ``max_rate_hz``: at most that many times per wall-clock second
    (0: no cap); ``scene_every_s``: send the scene again that often (None: only when it changes and to new
    subscribers); ``keep_events``: events kept for late subscribers.
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, every: int = 1,
                 max_rate_hz: float = 0.0, scene_every_s: float | None = None, keep_events: int = KEEP_EVENTS,
                 name: str = "dynabrain"):
        if host not in ("127.0.0.1", "localhost", "::1"):
            raise DynabrainError(f"the live view serves on loopback only, not on {host!r}")
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise DynabrainError(f"the live view's every must be a whole number of ticks >= 1, got {every!r}")
        self.host, self.requested_port, self.name, self.every = host, port, name, every
        self.min_interval = 1.0 / max_rate_hz if max_rate_hz > 0 else 0.0
        self.scene_every_s = scene_every_s
        self.server: Any = None
        self.origin_ns = 0
        """The log time of tick 0 (as in a log: the wall-clock time at `attach`, less that tick's simulated time)."""
        self.sent = 0
        """Ticks sent."""
        self._ctx: Any = None
        self._numbers = FieldNumbers()
        self._codecs: dict[tuple, BusCodec] = {}
        self._codec: BusCodec | None = None
        self._bus: Any = None
        self._bus_channels: dict[int, Any] = {}
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
        self._lock = threading.Lock()  # the latest messages, and sending them
        self._latest: dict[int, tuple[bytes, int]] = {}  # channel id -> its latest message and log time
        self._recent: deque[tuple[bytes, int]] = deque(maxlen=keep_events)

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def attach(self, world: Any) -> LiveView:
        with world.lock():
            self._ctx = foxglove.Context()
            self._dt = world.dt_ns
            view = WorldView(world)
            self.origin_ns = time.time_ns() - view.tick * self._dt
            self._events = self._proto_channel(TOPIC_EVENTS, Log)
            if view.core is not None:
                self._poses = PoseCodec(view.core.bodies())
                self._scene = SceneDrawing(view.core)
                self._tf = self._proto_channel(TOPIC_TF, FrameTransforms)
                self._scene_ch = self._proto_channel(TOPIC_SCENE, SceneUpdate)
            self._publish(view)
            self.server = self._start()
            world.observe(self)
        return self

    def _start(self) -> Any:
        listener = _Latest(self)
        try:
            return foxglove.start_server(name=self.name, host=self.host, port=self.requested_port, context=self._ctx,
                                         server_listener=listener)
        except RuntimeError as exc:
            if self.requested_port == 0 or "bind" not in str(exc).lower():
                raise DynabrainError(f"the live view cannot start its WebSocket server: {exc}") from None
            _log.warning("port %s is taken; the live view uses another", self.requested_port)
            return foxglove.start_server(name=self.name, host=self.host, port=0, context=self._ctx,
                                         server_listener=listener)

    def _proto_channel(self, topic: str, message_class: type, metadata: dict[str, str] | None = None) -> Any:
        schema = foxglove.Schema(name=message_class.DESCRIPTOR.full_name, encoding="protobuf",
                                 data=foxglove_descriptor(message_class))
        return foxglove.Channel(topic, schema=schema, message_encoding="protobuf", context=self._ctx,
                                metadata=metadata)

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

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    # -- publishing -----------------------------------------------------------------------------------
    def _publish(self, view: WorldView) -> None:
        bus = view.bus()
        if self._dirty or self._codec is None or bus.size != self._codec.size:
            self._new_layout(view)
        tick = view.tick
        t_ns = self.origin_ns + tick * self._dt
        row = bus[None, :]
        self._send(self._bus, self._codec.encode(row, [tick], [self._epoch], self._dt)[0].tobytes(), t_ns)
        if self._poses is not None:
            ext = row
            if self._missing:
                extra = np.concatenate([np.concatenate(view.core.body_pose(b)) for b in self._missing])
                ext = np.concatenate([row, extra[None, :]], axis=1)
            pose = ext[:, self._cols]
            self._send(self._tf, self._poses.encode(pose[:, :, :3], pose[:, :, 3:], np.array([t_ns]))[0].tobytes(),
                       t_ns)
            now = time.monotonic()
            if self._scene_due or (self.scene_every_s is not None and now - self._last_scene >= self.scene_every_s):
                self._scene_due, self._last_scene = False, now
                self._send(self._scene_ch, self._scene.encode(t_ns), t_ns)
        self.sent += 1

    def _send(self, channel: Any, data: bytes, t_ns: int) -> None:
        with self._lock:
            self._latest[channel.id()] = (data, t_ns)
            channel.log(data, log_time=t_ns)

    def _new_layout(self, view: WorldView) -> None:
        slots, size = view.signal_slots(), view.bus().size
        signature = (*sorted((n, o, tuple(sh), u) for n, (o, sh, u) in slots.items()), size)
        codec = self._codecs.get(signature)
        if codec is None:
            codec = self._codecs[signature] = BusCodec.from_view(slots, size, self._numbers, len(self._codecs) + 1)
        if codec is not self._codec:
            if self._bus is not None:  # one schema per topic: the old layout's topic goes away
                with self._lock:
                    self._latest.pop(self._bus.id(), None)
                self._bus.close()
            schema = foxglove.Schema(name=codec.schema_name, encoding="protobuf", data=codec.descriptor())
            self._bus = foxglove.Channel(bus_topic(codec.key), schema=schema, message_encoding="protobuf",
                                         context=self._ctx, metadata=codec.metadata())
            self._codec = codec
        if self._poses is not None:
            self._cols, self._missing = pose_columns(view.core.name, self._poses.bodies, self._codec)
        self._dirty = False

    def _send_event(self, kind: str, tick: int, detail: dict, source: str = "api") -> None:
        self._seq += 1
        body = {"seq": self._seq, "tick": tick, "time": tick * self._dt / 1e9, "epoch": self._epoch, "kind": kind,
                "source": source, "detail": detail}
        t_ns = self.origin_ns + tick * self._dt
        data = log_message(t_ns, event_level(kind, detail), event_bytes(body).decode(), kind)
        with self._lock:
            self._recent.append((data, t_ns))
            self._events.log(data, log_time=t_ns)

    def _catch_up(self, client_id: int, channel_id: int) -> None:
        """Send a client that subscribed to a channel its latest message (the recent ones: events)."""
        with self._lock:
            if self._events is not None and channel_id == self._events.id():
                for data, t_ns in self._recent:
                    self._events.log(data, log_time=t_ns, sink_id=client_id)
                return
            latest = self._latest.get(channel_id)
            channel = next((c for c in (self._bus, self._tf, self._scene_ch) if c is not None and c.id() == channel_id),
                           None)
            if latest is not None and channel is not None:
                channel.log(latest[0], log_time=latest[1], sink_id=client_id)


class _Latest(ServerListener):
    """Tells the view about each subscription; the view answers from a thread of its own (the server
    calls this on its own thread, where sending is not safe to do under the view's lock)."""

    def __init__(self, view: LiveView):
        self.view = view

    def on_subscribe(self, client: Any, channel: Any) -> None:
        threading.Thread(target=self.view._catch_up, args=(client.id, channel.id), daemon=True,
                         name="dynabrain-live-catch-up").start()
