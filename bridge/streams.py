"""What a served world publishes: state frames each tick or decimated (``dynabrain/<world>/state``) and
events (``dynabrain/<world>/events``: edits, rollbacks, errors, brains and robots coming and going).

`StateStream` is an observer: it runs on the stepping thread under the world lock, so it only packs
bytes and hands them to Zenoh (which queues them); it never calls back into the world.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from typing import Any

import zenoh

from dynabrain.orchestrator.kernel.observers import Observer, WorldEvent, WorldView

from . import protocol as p
from .calls import STREAM_VIEW, WorldService
from .zenoh_io import FRAME, JSON

_log = logging.getLogger("dynabrain.bridge")


class EventSink:
    """Publishes events as JSON on ``dynabrain/<world>/events``."""

    def __init__(self, session: zenoh.Session, world: str):
        self._pub = session.declare_publisher(p.key(world, "events"), encoding=JSON)
        self.tick_of: Callable[[], int] = lambda: 0

    def emit(self, kind: str, /, tick: int | None = None, source: str = "bridge", **detail: Any) -> None:
        msg = {"tick": self.tick_of() if tick is None else tick, "kind": kind, "detail": p.plain(detail),
               "source": source}
        try:
            self._pub.put(p.encode(msg))
        except Exception as exc:  # a closed session while shutting down: nothing to tell anyone
            _log.debug("event %s not published: %s", kind, exc)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._pub.undeclare()


class StateStream(Observer):
    """State frames of the service's stream view every ``decimate`` ticks, and the world's events."""

    def __init__(self, session: zenoh.Session, world: str, service: WorldService, events: EventSink,
                 decimate: int = 1):
        if decimate < 1:
            raise ValueError("decimate must be >= 1")
        self._service = service
        self._events = events
        self._decimate = decimate
        self._pub = (session.declare_publisher(p.key(world, "state"), encoding=FRAME)
                     if service.has_view(STREAM_VIEW) else None)
        self.tick_hooks: list[Callable[[WorldView], None]] = []
        self.frames_sent = 0

    def on_tick(self, view: WorldView) -> None:
        for hook in self.tick_hooks:
            hook(view)
        if self._pub is None or view.tick % self._decimate:
            return
        try:
            payload = self._service.frame(self._service.get_view(STREAM_VIEW))
        except Exception as exc:  # the stream's signals left with a module: say so once, stop streaming
            self._pub = None
            self._events.emit("stream_stopped", tick=view.tick, reason=str(exc))
            return
        self._pub.put(payload)
        self.frames_sent += 1

    def on_rollback(self, view: WorldView, from_tick: int) -> None:
        self._events.emit("rollback", tick=view.tick, source="world", from_tick=from_tick)

    def on_event(self, view: WorldView, event: WorldEvent) -> None:
        if self._service.applying_inputs and event.kind in ("set", "param"):
            return  # streamed inputs: too many to echo; their errors are reported
        self._events.emit(event.kind, tick=event.tick, source=event.source, **event.detail)

    def on_close(self, view: WorldView) -> None:
        self.close()

    def close(self) -> None:
        pub, self._pub = self._pub, None
        if pub is not None:
            with contextlib.suppress(Exception):
                pub.undeclare()
