"""Live view: a running world served to the Foxglove app over its WebSocket protocol, on loopback.

The same channels as a log (`logs.schema`): ``/bus``, ``/tf``, ``/scene``, ``/events``, encoded the
same way, through foxglove-sdk's server bound to 127.0.0.1 (port 8765 by default, the app's default;
another free port when that one is taken; 0 asks for any). The view follows the world at most
``max_rate_hz`` times per wall-clock second (a world stepping faster than the app can draw is sampled)
and at once after every rollback; every event is sent. The scene is sent again every ``scene_every_s``
seconds for clients that connect late, and after each `make`.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import foxglove
import numpy as np
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from ..kernel.errors import DynabrainError
from ..kernel.observers import Observer, WorldEvent, WorldView
from .scene import SceneDrawing
from .schema import (
    EVENT_SCHEMA,
    TOPIC_BUS,
    TOPIC_EVENTS,
    TOPIC_SCENE,
    TOPIC_TF,
    BusCodec,
    FieldNumbers,
    PoseCodec,
    event_bytes,
    foxglove_descriptor,
    pose_columns,
)

_log = logging.getLogger("dynabrain.mcap")
DEFAULT_PORT = 8765


class LiveView(Observer):
    """Serves a world to Foxglove (see the module docstring). ``attach`` starts the server."""

    def __init__(self, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, max_rate_hz: float = 60.0,
                 scene_every_s: float = 1.0, name: str = "dynabrain"):
        if host not in ("127.0.0.1", "localhost", "::1"):
            raise DynabrainError(f"the live view serves on loopback only, not on {host!r}")
        self.host, self.requested_port, self.name = host, port, name
        self.min_interval = 1.0 / max_rate_hz if max_rate_hz > 0 else 0.0
        self.scene_every_s = scene_every_s
        self.server: Any = None
        self._ctx: Any = None
        self._numbers = FieldNumbers()
        self._codec: BusCodec | None = None
        self._bus: Any = None
        self._dirty = True
        self._last = 0.0
        self._last_scene = -1e9
        self._epoch = 0
        self._seq = 0
        self._poses: PoseCodec | None = None
        self._scene: SceneDrawing | None = None

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def attach(self, world: Any) -> LiveView:
        with world.lock():
            self._ctx = foxglove.Context()
            self.server = self._start()
            self._dt = world.dt_ns
            view = WorldView(world)
            self._events = foxglove.Channel(TOPIC_EVENTS, schema=EVENT_SCHEMA, context=self._ctx)
            if view.core is not None:
                self._poses = PoseCodec(view.core.bodies())
                self._scene = SceneDrawing(view.core)
                self._tf = self._proto_channel(TOPIC_TF, FrameTransforms)
                self._scene_ch = self._proto_channel(TOPIC_SCENE, SceneUpdate)
            self._publish(view)
            world.observe(self)
        return self

    def _start(self) -> Any:
        try:
            return foxglove.start_server(name=self.name, host=self.host, port=self.requested_port, context=self._ctx)
        except RuntimeError as exc:
            if self.requested_port == 0 or "bind" not in str(exc).lower():
                raise DynabrainError(f"the live view cannot start its WebSocket server: {exc}") from None
            _log.warning("port %s is taken; the live view uses another", self.requested_port)
            return foxglove.start_server(name=self.name, host=self.host, port=0, context=self._ctx)

    def _proto_channel(self, topic: str, message_class: type) -> Any:
        schema = foxglove.Schema(name=message_class.DESCRIPTOR.full_name, encoding="protobuf",
                                 data=foxglove_descriptor(message_class))
        return foxglove.Channel(topic, schema=schema, message_encoding="protobuf", context=self._ctx)

    # -- observer hooks -------------------------------------------------------------------------------
    def on_tick(self, view: WorldView) -> None:
        now = time.monotonic()
        if now - self._last >= self.min_interval:
            self._publish(view, now)

    def on_rollback(self, view: WorldView, from_tick: int) -> None:
        self._epoch += 1
        self._dirty = True
        self._send_event("rollback", view.tick, {"from_tick": from_tick, "to_tick": view.tick, "epoch": self._epoch})
        self._last_scene = -1e9
        self._publish(view)

    def on_event(self, view: WorldView, event: WorldEvent) -> None:
        if event.kind in ("module_added", "module_removed"):
            self._dirty = True
        elif event.kind == "make":
            self._last_scene = -1e9
        self._send_event(event.kind, event.tick, event.detail, event.source)

    def on_close(self, view: WorldView) -> None:
        self.close()

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    # -- publishing -----------------------------------------------------------------------------------
    def _publish(self, view: WorldView, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        self._last = now
        bus = view.bus()
        if self._dirty or self._codec is None or bus.size != self._codec.size:
            self._new_layout(view)
        tick, t_ns = view.tick, view.tick * self._dt
        row = bus[None, :]
        self._bus.log(self._codec.encode(row, [tick], [self._epoch], self._dt)[0].tobytes(), log_time=t_ns)
        if self._poses is not None:
            ext = row
            if self._missing:
                extra = np.concatenate([np.concatenate(view.core.body_pose(b)) for b in self._missing])
                ext = np.concatenate([row, extra[None, :]], axis=1)
            pose = ext[:, self._cols]
            self._tf.log(self._poses.encode(pose[:, :, :3], pose[:, :, 3:], np.array([t_ns]))[0].tobytes(),
                         log_time=t_ns)
            if now - self._last_scene >= self.scene_every_s:
                self._last_scene = now
                self._scene_ch.log(self._scene.encode(t_ns), log_time=t_ns)

    def _new_layout(self, view: WorldView) -> None:
        key = (self._codec.key + 1) if self._codec is not None else 1
        self._codec = BusCodec.from_view(view.signal_slots(), view.bus().size, self._numbers, key)
        if self._bus is not None:
            self._bus.close()
        schema = foxglove.Schema(name=self._codec.schema_name, encoding="protobuf", data=self._codec.descriptor())
        self._bus = foxglove.Channel(TOPIC_BUS, schema=schema, message_encoding="protobuf", context=self._ctx,
                                     metadata=self._codec.metadata())
        if self._poses is not None:
            self._cols, self._missing = pose_columns(view.core.name, self._poses.bodies, self._codec)
        self._dirty = False

    def _send_event(self, kind: str, tick: int, detail: dict, source: str = "api") -> None:
        self._seq += 1
        body = {"seq": self._seq, "tick": tick, "time": tick * self._dt / 1e9, "epoch": self._epoch, "kind": kind,
                "source": source, "detail": detail}
        self._events.log(event_bytes(body), log_time=tick * self._dt)
