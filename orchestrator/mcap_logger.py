"""The MCAP logger: an observer that records a run to one file (what it holds: `mcap_schema`).

    logger = McapLogger("run.mcap").attach(world, scenario)   # right after the world is built
    world.tick(1000)
    world.close()                                             # or logger.close()

**Rollbacks.** A tick's messages wait in memory for ``window`` ticks (plus a batch of ``batch``)
before they are written. A rollback marks the waiting ticks it discards, and they are written, in
the order they were produced, to the ``/discarded/...`` channels; ``/bus``, ``/tf`` and ``/scene``
keep what finally happened. Every rollback is an event on ``/events`` (``from_tick``, ``to_tick``,
``cause``: backtick, restore or failed_tick), and every message carries its *epoch* (rollbacks
before it) in the MCAP ``sequence`` field. The rule readers apply is: for each tick, the run is the
message produced last, and a rollback to tick k discards every message of a later tick produced before
it. A rollback that reaches further back than the window finds ticks already written; the file is
then rewritten on close (`mcap_recover.rewrite`) so that those, too, move to ``/discarded/...``.
``dynabrain run`` cannot roll back (except a failed tick, which discards nothing), so it uses no window.

**Crash safety.** A kill loses the ticks still waiting (the ``window``, plus at most ``batch`` ticks or
``flush_s / 2`` seconds of them) and the chunk being filled (at most ``chunk_bytes`` of messages, or
``flush_s`` seconds of them); `dynabrain log recover` turns what is left into a valid file. With the
defaults and no window (``dynabrain run``), a run at real time loses under half a second.

**Cost.** A tick costs a copy of the bus; a batch is encoded and written with a few numpy operations
per channel (see `bench/logging.py`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from collections import deque
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from .errors import DynabrainError
from .mcap_meta import run_metadata
from .mcap_scene import SceneDrawing
from .mcap_schema import (
    DISCARDED,
    EVENT_SCHEMA,
    METADATA_NAME,
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
from .mcap_write import McapWriter
from .observers import Observer, WorldEvent, WorldView

_log = logging.getLogger("dynabrain.mcap")


class _Tick:
    """A tick waiting to be written: its bus row is row ``slot`` of its layout's `_Rows`."""

    __slots__ = ("codec", "discarded", "epoch", "extra", "scene", "slot", "tick")

    def __init__(self, tick: int, epoch: int, codec: BusCodec, slot: int, extra: np.ndarray | None,
                 scene: bytes | None):
        self.tick, self.epoch, self.codec, self.slot, self.extra, self.scene = tick, epoch, codec, slot, extra, scene
        self.discarded = False


class _Rows:
    """The bus rows of one layout waiting to be written, in a preallocated ring used in order, so a
    batch of consecutive ticks is a slice of it (no copies to gather them)."""

    def __init__(self, capacity: int, size: int):
        self.rows = np.empty((capacity, size))
        self.next = 0

    def put(self, bus: np.ndarray) -> int:
        slot = self.next
        np.copyto(self.rows[slot], bus)
        self.next = (slot + 1) % len(self.rows)
        return slot


class McapLogger(Observer):
    """Records a world's run to an MCAP file. See the module docstring.

    ``decimate``: poses every that many ticks; ``scene_every``: the scene every that many ticks
    (default: one simulated second) and after each `make`; ``window``: ticks held back for rollbacks;
    ``batch``: ticks encoded and written together (at most ``flush_s / 2`` s after the first is due);
    ``chunk_bytes``, ``flush_s``, ``level``: chunk size and age, zstd level.
    """

    def __init__(self, path: str | os.PathLike[str], *, decimate: int = 1, scene_every: int | None = None,
                 window: int = 64, batch: int = 256, chunk_bytes: int = 1 << 20, flush_s: float = 0.25,
                 level: int = 1):
        for name, value, low in (("decimate", decimate, 1), ("window", window, 0), ("batch", batch, 1),
                                 ("scene_every", scene_every or 1, 1), ("chunk_bytes", chunk_bytes, 1)):
            if not isinstance(value, int) or value < low:
                raise DynabrainError(f"McapLogger: {name} must be an integer >= {low}, got {value!r}")
        self.path = os.fspath(path)
        self.decimate, self.scene_every, self.window, self.batch = decimate, scene_every, window, batch
        self._writer_args = {"chunk_bytes": chunk_bytes, "flush_s": flush_s, "level": level}
        self._max_wait = flush_s / 2
        self._drained_at = time.monotonic()
        self._writer: McapWriter | None = None
        self._pending: deque[_Tick] = deque()
        self._numbers = FieldNumbers()
        self._codecs: dict[tuple, BusCodec] = {}
        self._rows: dict[int, _Rows] = {}
        self._capacity = window + batch + 8
        self._channels: dict[tuple[str, int], int] = {}
        self._pose_index: dict[int, tuple[np.ndarray, list[str]]] = {}
        self._codec: BusCodec | None = None
        self._missing: list[str] = []
        self._epoch = 0
        self._seq = 0
        self._dirty = True
        self._scene: SceneDrawing | None = None
        self._poses: PoseCodec | None = None
        self._next_scene = 0
        self._written_max = -1
        self._compact = False
        self._restoring = False
        self._restored_snapshot: int | None = None
        self._failing: int | None = None
        self._schema_ids: dict[int | str, int] = {}
        self._lock: Any = None
        self._world: Any = None
        self.closed = False

    # -- attaching ------------------------------------------------------------------------------------
    def attach(self, world: Any, scenario: Any = None) -> McapLogger:
        """Start recording ``world`` (built from ``scenario``, when there is one) at its current tick."""
        with world.lock():
            view = WorldView(world)
            self._world, self._lock, self._dt = world, world.lock(), world.dt_ns
            if self.scene_every is None:
                self.scene_every = max(1, round(1e9 / self._dt))
            self._writer = McapWriter(self.path, profile="dynabrain", **self._writer_args)
            try:
                settings = {"decimate": self.decimate, "scene_every": self.scene_every, "window": self.window,
                            "batch": self.batch, **self._writer_args}
                self._writer.add_metadata(METADATA_NAME, run_metadata(world, scenario, settings))
                self._channel(TOPIC_EVENTS, lambda: self._json_channel(TOPIC_EVENTS))
                if view.core is not None:
                    self._scene = SceneDrawing(view.core)
                    self._poses = PoseCodec(view.core.bodies())
                self._refresh_layout(view)
                self._push(view, view.bus())
            except BaseException:
                self._writer.close()
                raise
            world.observe(self)
        return self

    # -- observer hooks -------------------------------------------------------------------------------
    def on_tick(self, view: WorldView) -> None:
        if self.closed:
            return
        if self._dirty:
            self._refresh_layout(view)
        bus = view.bus()
        if bus.size != self._codec.size:
            self._refresh_layout(view)
        self._push(view, bus)
        waiting = len(self._pending) - self.window
        if waiting >= self.batch or (waiting > 0 and time.monotonic() - self._drained_at >= self._max_wait):
            self._drain(waiting)

    def on_event(self, view: WorldView, event: WorldEvent) -> None:
        if self.closed:
            return
        if event.kind == "restore":
            self._restoring = True
            self._restored_snapshot = event.detail.get("snapshot")
        elif event.kind == "error":
            self._failing = event.detail.get("failed_tick")
        elif event.kind in ("module_added", "module_removed"):
            self._dirty = True
        elif event.kind == "make":
            self._next_scene = view.tick
        self._event(event.kind, event.tick, event.detail, event.source)

    def on_rollback(self, view: WorldView, from_tick: int) -> None:
        if self.closed:
            return
        to = view.tick
        cause = "restore" if self._restoring else "failed_tick" if self._failing == from_tick == to else "backtick"
        self._restoring, self._failing = False, None
        last = to - 1 if cause == "restore" else to  # a restore replaces tick `to` itself
        for item in reversed(self._pending):
            if item.discarded:
                continue
            if item.tick <= last:
                break
            item.discarded = True
        if self._written_max > last:
            self._compact = True
        self._written_max = min(self._written_max, last)
        self._epoch += 1
        detail = {"from_tick": from_tick, "to_tick": to, "cause": cause, "epoch": self._epoch}
        if cause == "restore" and self._restored_snapshot:
            detail["snapshot"] = self._restored_snapshot
        self._event("rollback", to, detail, "api")
        self._dirty = True
        self._next_scene = to
        if cause == "restore":
            self._refresh_layout(view)
            self._push(view, view.bus())

    def on_close(self, view: WorldView) -> None:
        try:
            self.close()
        except Exception as exc:  # the world suppresses observer errors at close; do not lose this one
            _log.error("closing the MCAP log %s failed: %s", self.path, exc)

    # -- results and closing ----------------------------------------------------------------------------
    def log_result(self, result: Any) -> None:
        """Record a run's expectation results and its end (`dynabrain run` calls this)."""
        if self._lock is None or self.closed:
            raise DynabrainError(f"the log {self.path} is not recording (attach it to a world first)")
        with self._lock:
            tick = int(result.ticks)
            for exp in result.expectations:
                detail = {"name": exp.label, "that": exp.that, "passed": bool(exp.passed), "detail": exp.detail,
                          "from_tick": exp.start, "to_tick": exp.end}
                self._event("expect", min(exp.end, tick), detail, "log")
            self._event("run_end", tick, {"ticks": tick, "sim_time": result.sim_time, "wall_time": result.wall_time,
                                          "error": result.error, "ok": result.ok}, "log")

    def close(self) -> None:
        """Write what is waiting, the summary and the footer; rewrite the file if a rollback reached
        ticks already written (see the module docstring). Idempotent."""
        if self.closed or self._writer is None:
            return
        with self._lock:
            self.closed = True
            with contextlib.suppress(ValueError):  # not observing any more (the caller took it off)
                self._world.unobserve(self)
            self._drain(len(self._pending))
            self._writer.finish()
        if self._compact:
            from .mcap_recover import rewrite

            tmp = self.path + ".compacting"
            rewrite(self.path, tmp)
            os.replace(tmp, self.path)

    @property
    def stats(self) -> dict[str, float]:
        w = self._writer
        return {"messages": w.messages if w else 0, "chunks": w.chunks if w else 0,
                "bytes": w.bytes_written if w else 0, "epoch": self._epoch,
                "writer_cpu_s": w.thread_cpu_s if w else 0.0}

    # -- internals ------------------------------------------------------------------------------------
    def _push(self, view: WorldView, bus: np.ndarray) -> None:
        tick = view.tick
        extra = None
        if self._missing and tick % self.decimate == 0:
            core = view.core
            extra = np.concatenate([np.concatenate(core.body_pose(b)) for b in self._missing])
        scene = None
        if self._scene is not None and tick >= self._next_scene:
            scene = self._scene.encode(tick * self._dt)
            self._next_scene = tick + self.scene_every
        if len(self._pending) >= self._capacity:  # a ring is full (a restore pushed one more): write first
            self._drain(len(self._pending) - self.window)
        rows = self._rows.get(self._codec.key)
        if rows is None:
            rows = self._rows[self._codec.key] = _Rows(self._capacity, self._codec.size)
        self._pending.append(_Tick(tick, self._epoch, self._codec, rows.put(bus), extra, scene))

    def _refresh_layout(self, view: WorldView) -> None:
        slots = view.signal_slots()
        size = view.bus().size
        signature = (*sorted((n, o, tuple(sh), u) for n, (o, sh, u) in slots.items()), size)
        codec = self._codecs.get(signature)
        if codec is None:
            codec = BusCodec.from_view(slots, size, self._numbers, len(self._codecs) + 1)
            self._codecs[signature] = codec
            self._pose_index[codec.key] = self._pose_plan(view, codec)
            detail: dict[str, Any] = {"layout": codec.key, "signals": len(codec.slots), "values": size}
            if self._codec is not None:
                detail["added"] = sorted(set(codec.by_name) - set(self._codec.by_name))
                detail["removed"] = sorted(set(self._codec.by_name) - set(codec.by_name))
            self._event("layout", view.tick, detail, "log")
        self._codec = codec
        self._missing = self._pose_index[codec.key][1]
        self._dirty = False

    def _pose_plan(self, view: WorldView, codec: BusCodec) -> tuple[np.ndarray, list[str]]:
        if self._poses is None:
            return np.zeros((0, 7), dtype=np.intp), []
        return pose_columns(view.core.name, self._poses.bodies, codec)

    def _drain(self, n: int) -> None:
        self._drained_at = time.monotonic()
        group: list[_Tick] = []
        for _ in range(min(n, len(self._pending))):
            item = self._pending.popleft()
            if group and (item.codec is not group[0].codec or item.discarded != group[0].discarded
                          or item.slot != group[-1].slot + 1):
                self._write(group)
                group = []
            group.append(item)
        if group:
            self._write(group)

    def _write(self, group: list[_Tick]) -> None:
        """Encode a group of consecutive ticks (one layout, consecutive ring rows) straight into the chunk."""
        codec, discarded = group[0].codec, group[0].discarded
        prefix = DISCARDED if discarded else ""
        ticks = np.array([it.tick for it in group], dtype=np.int64)
        epochs = np.array([it.epoch for it in group], dtype=np.int64)
        rows = self._rows[codec.key].rows[group[0].slot:group[0].slot + len(group)]
        t_ns = ticks * self._dt
        w, dt = self._writer, self._dt

        def bus(out: np.ndarray, part: slice) -> None:
            codec.encode(rows[part], ticks[part], epochs[part], dt, out=out)

        w.add_encoded(self._bus_channel(codec, prefix), t_ns, epochs, codec.length, bus)
        if not discarded:
            self._written_max = max(self._written_max, int(ticks[-1]))
        if self._poses is None:
            return
        due = np.flatnonzero(ticks % self.decimate == 0)
        if len(due):
            cols, missing = self._pose_index[codec.key]
            ext = rows if len(due) == len(rows) else rows[due]
            if missing:
                ext = np.concatenate([ext, np.stack([group[i].extra for i in due])], axis=1)
            pose, times = ext[:, cols], t_ns[due]

            def poses(out: np.ndarray, part: slice) -> None:
                self._poses.encode(pose[part, :, :3], pose[part, :, 3:], times[part], out=out)

            w.add_encoded(self._proto_channel(prefix + TOPIC_TF, FrameTransforms), times, epochs[due],
                          self._poses.length, poses)
        for item in group:
            if item.scene is not None:
                w.add_message(self._proto_channel(prefix + TOPIC_SCENE, SceneUpdate), item.tick * self._dt,
                              item.scene, item.epoch)

    def _event(self, kind: str, tick: int, detail: dict, source: str) -> None:
        self._seq += 1
        body = {"seq": self._seq, "tick": tick, "time": tick * self._dt / 1e9, "epoch": self._epoch, "kind": kind,
                "source": source, "detail": detail}
        self._writer.add_message(self._channels[(TOPIC_EVENTS, 0)], tick * self._dt, event_bytes(body), self._epoch)

    # -- channels -------------------------------------------------------------------------------------
    def _channel(self, topic: str, make, key: int = 0) -> int:
        cid = self._channels.get((topic, key))
        if cid is None:
            cid = self._channels[(topic, key)] = make()
        return cid

    def _json_channel(self, topic: str) -> int:
        sid = self._writer.add_schema("dynabrain.Event", "jsonschema", json.dumps(EVENT_SCHEMA).encode())
        return self._writer.add_channel(topic, "json", sid)

    def _bus_channel(self, codec: BusCodec, prefix: str) -> int:
        def make() -> int:
            sid = self._schema_ids.get(codec.key)
            if sid is None:
                sid = self._schema_ids[codec.key] = self._writer.add_schema(codec.schema_name, "protobuf",
                                                                           codec.descriptor())
            return self._writer.add_channel(prefix + TOPIC_BUS, "protobuf", sid, codec.metadata())

        return self._channel(prefix + TOPIC_BUS, make, codec.key)

    def _proto_channel(self, topic: str, message_class: type) -> int:
        def make() -> int:
            name = message_class.DESCRIPTOR.full_name
            sid = self._schema_ids.get(name)
            if sid is None:
                sid = self._schema_ids[name] = self._writer.add_schema(name, "protobuf",
                                                                      foxglove_descriptor(message_class))
            return self._writer.add_channel(topic, "protobuf", sid)

        return self._channel(topic, make)
