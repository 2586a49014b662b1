"""A running world streamed to Rerun's web viewer (``dynabrain serve --view``): what `rerun_view` draws from a
log, drawn as the world goes.

`RerunLive` is an observer. ``attach`` starts the ``rerun`` program serving the web viewer on loopback (it
also takes the stream: `rerun_view.serve_rrd` with no file) and connects a recording stream to it; then,
every ``every`` ticks, it sends the bodies' poses (``world/<body>``, `Transform3D`) and the small signals
(``signals/...``), on the ``sim_time`` timeline. The scene (`scene.SceneDrawing`, the live Foxglove view's
drawing) is sent at the start and after each ``make`` and rollback; events go to ``events`` (and
``expectations/<label>``); each future a brain imagines and keeps (`World.imagine`) is drawn under
``imagined/<name>/<branch>/`` at its own ticks, translucent, beside what happens, and cleared after its last.
The viewer keeps what it was sent, so a browser that opens it late sees the run from its start.
"""

from __future__ import annotations

import logging
import socket
import time
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError
from ..kernel.observers import Imagined, Observer, WorldEvent, WorldView
from .rerun_view import (
    MAX_COMPONENTS,
    TIMELINE,
    WORLD,
    blueprint,
    draw_entity,
    entity_path,
    require_rerun,
    serve_rrd,
    signal_path,
    viewer_url,
)
from .scene import INFINITE_PLANE, SceneDrawing
from .schema import imagined_frame

_log = logging.getLogger("dynabrain.rerun")
START_WAIT_S = 20.0
"""How long ``attach`` waits for the rerun program to serve."""


class RerunLive(Observer):
    """See the module docstring. ``web_port``/``grpc_port``: the viewer's and the stream's ports on loopback;
    ``rate_hz``: poses and signals sent per second of simulated time (0: every tick)."""

    def __init__(self, *, web_port: int, grpc_port: int, rate_hz: float = 50.0):
        self.web_port, self.grpc_port, self.rate_hz = web_port, grpc_port, rate_hz
        self.url = viewer_url(web_port, grpc_port)
        self.sent = 0
        """Ticks sent."""
        self._rr: Any = None
        self._rec: Any = None
        self._proc: Any = None
        self._scene: SceneDrawing | None = None
        self._every = 1
        self._dt_s = 0.0
        self._plane_m = INFINITE_PLANE

    def attach(self, world: Any) -> RerunLive:
        """Serve the viewer, connect, and observe ``world`` (a viewer that does not start raises
        `DynabrainError`, the world untouched)."""
        rr = self._rr = require_rerun()
        self._proc = serve_rrd(None, web_port=self.web_port, grpc_port=self.grpc_port)
        end = time.monotonic() + START_WAIT_S
        while not (_listening(self.web_port) and _listening(self.grpc_port)):
            if self._proc.poll() is not None or time.monotonic() > end:
                self.close()
                raise DynabrainError(f"the rerun web viewer did not start on ports {self.web_port}, {self.grpc_port}")
            time.sleep(0.1)
        rec = self._rec = rr.RecordingStream("dynabrain")
        rec.connect_grpc(f"rerun+http://127.0.0.1:{self.grpc_port}/proxy", default_blueprint=blueprint())
        rec.send_recording_name(world.name)
        rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        with world.lock():
            view = WorldView(world)
            self._dt_s = world.dt_ns / 1e9
            self._every = max(1, round(1 / (self.rate_hz * self._dt_s))) if self.rate_hz > 0 else 1
            if view.core is not None:
                self._scene = SceneDrawing(view.core)
                reach = max((float(np.abs(view.core.body_pose(b)[0][:2]).max()) for b in self._scene.bodies),
                            default=1.0)
                self._plane_m = min(2 * reach + 1.0, INFINITE_PLANE)
            self._draw_scene(view)
            self._publish(view)
            world.observe(self)
        return self

    # -- observer hooks -------------------------------------------------------------------------------
    def on_tick(self, view: WorldView) -> None:
        if view.tick % self._every == 0:
            self._publish(view)

    def on_rollback(self, view: WorldView, from_tick: int) -> None:
        self._text(view.tick, f"rollback {from_tick} -> {view.tick}", "WARN")
        self._draw_scene(view)
        self._publish(view)

    def on_event(self, view: WorldView, event: WorldEvent) -> None:
        if event.kind == "layout":
            return
        if event.kind == "make":
            self._draw_scene(view)
        detail = event.detail if isinstance(event.detail, dict) else {}
        failed = event.kind == "error" or (event.kind == "expect" and not detail.get("passed", True))
        self._text(event.tick, f"{event.kind} {detail}"[:300], "WARN" if failed else "INFO")

    def on_imagined(self, view: WorldView, imagined: Imagined) -> None:
        rr, rec = self._rr, self._rec
        root = f"imagined/{imagined.name}/{imagined.branch}"
        times = (imagined.start_tick + 1 + np.arange(imagined.ticks)) * self._dt_s
        index = [rr.TimeColumn(TIMELINE, duration=times)]
        core = view.core.name if view.core is not None else None
        drawn = []
        for body in self._scene.bodies if self._scene is not None else []:
            pos, quat = imagined.signals.get(f"{core}.{body}.pos"), imagined.signals.get(f"{core}.{body}.quat")
            if pos is not None and quat is not None:
                rec.send_columns(entity_path(imagined_frame(imagined.name, imagined.branch, body), "/" + root),
                                 indexes=index, columns=rr.Transform3D.columns(
                                     translation=np.asarray(pos).reshape(-1, 3),
                                     quaternion=np.asarray(quat).reshape(-1, 4)[:, [1, 2, 3, 0]]))
                drawn.append(body)
        if drawn and self._scene is not None:
            frames = [imagined_frame(imagined.name, imagined.branch, b) for b in drawn]
            from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

            rec.set_time(TIMELINE, duration=float(times[0]))
            update = SceneUpdate.FromString(self._scene.imagined(drawn, frames, 0, 0))
            for entity in update.entities:
                draw_entity(rr, rec, entity_path(entity.id, "/" + root), entity, self._plane_m)
        for signal, values in imagined.signals.items():
            data = np.asarray(values, dtype=np.float64).reshape(imagined.ticks, -1)
            if 0 < data.shape[1] <= MAX_COMPONENTS:
                rec.send_columns(signal_path(root + "/signals", signal), indexes=index,
                                 columns=_scalars(rr, data))
        rec.set_time(TIMELINE, duration=float(times[-1]) + self._dt_s)
        rec.log(root, rr.Clear(recursive=True))

    def on_close(self, view: WorldView) -> None:
        self.close()

    def close(self) -> None:
        """Flush the stream and stop the viewer. Idempotent."""
        rec, self._rec = self._rec, None
        if rec is not None:
            try:
                rec.flush(timeout_sec=2.0)
                rec.disconnect()
            except RuntimeError as exc:  # the viewer is gone already: nothing left to show
                _log.warning("rerun: the stream ended badly: %s", exc)
        if self._proc is not None:
            self._proc.kill()
            self._proc.wait()
            self._proc = None

    # -- sending --------------------------------------------------------------------------------------
    def _draw_scene(self, view: WorldView) -> None:
        if self._scene is None or self._rec is None:
            return
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

        self._rec.set_time(TIMELINE, duration=view.tick * self._dt_s)
        for entity in SceneUpdate.FromString(self._scene.encode(0)).entities:
            draw_entity(self._rr, self._rec, entity_path(entity.id, ""), entity, self._plane_m)

    def _publish(self, view: WorldView) -> None:
        rr, rec = self._rr, self._rec
        if rec is None:
            return
        rec.set_time(TIMELINE, duration=view.tick * self._dt_s)
        if self._scene is not None:
            core = view.core
            for body in self._scene.bodies:
                pos, quat = core.body_pose(body)
                rec.log(entity_path(body, ""),
                        rr.Transform3D(translation=pos, quaternion=np.asarray(quat)[[1, 2, 3, 0]]))
        bus = view.bus()
        for name, (offset, shape, _unit) in view.signal_slots().items():
            size = int(np.prod(shape, dtype=np.int64))
            if 0 < size <= MAX_COMPONENTS:
                rec.log(signal_path("signals", name), rr.Scalars(bus[offset:offset + size]))
        self.sent += 1

    def _text(self, tick: int, text: str, level: str) -> None:
        if self._rec is not None:
            self._rec.set_time(TIMELINE, duration=tick * self._dt_s)
            self._rec.log("events", self._rr.TextLog(text, level=level))


def _scalars(rr: Any, data: np.ndarray) -> Any:
    columns = rr.Scalars.columns(scalars=data if data.shape[1] > 1 else data[:, 0])
    return columns.partition([data.shape[1]] * len(data)) if data.shape[1] > 1 else columns


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0
