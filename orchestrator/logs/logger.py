"""The MCAP logger: an observer that records a run to one file (what it holds: `logs.schema`).

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
then rewritten on close (`logs.recover.rewrite`) so that those, too, move to ``/discarded/...``.
``dynabrain run`` cannot roll back (except a failed tick, which discards nothing), so it uses no window.

**Order.** Messages are written in log-time order (`logs.write`, `logs.sink`): log time is the run's
wall-clock start plus the simulated time (`logs.schema`). A rollback produces ticks again, at times
already written; such a log is rewritten in log-time order when it closes (`logs.recover.rewrite`,
which holds the file's messages in memory for that), with the ``/bus`` family, ``/tf`` and ``/scene``
holding the run and the discarded ticks on ``/discarded/...``, side by side at their times. Readers that
need the order in which ticks were produced sort by (epoch, tick) (`logs.read`).

**Imagined futures.** A branch the brain imagined and keeps (`World.imagine`; `on_imagined`) is
written at once to its own ``/imagined/<name>/<branch>/...`` channels, at its own future ticks, with an
``imagined`` event: it is not the run, so it never waits in the window and no rollback discards it.

**Crash safety.** The file is written by a child process (`logs.sink`). If the simulation's process
is killed, the child writes everything it was handed and finishes the file: only the ticks still
waiting in the simulation's process are lost (the ``window``, plus at most ``batch`` ticks or
``flush_s / 2`` seconds of them). If both die, the chunk being filled is lost too (at most
``chunk_bytes`` of messages, ``chunk_s`` of simulated time or ``flush_s`` seconds of them), and
`dynabrain log recover` turns what is left into a valid file. With the defaults and no window
(``dynabrain run``), a run at real time loses under half a second either way. A file damaged later (a
flipped bit, a bad copy) loses the chunks the damage touches: recover keeps every intact chunk after
them too.

**Cost.** The stepping thread copies the bus row into a preallocated block of shared memory (rows of
consecutive ticks of one layout and epoch: a row's tick is its block's first tick plus its index, so
a tick makes no Python object; one memoryview copy while nothing else is due: `McapLogger.on_tick`;
blocks are mapped with their pages, so no row faults one in; a layout's first ``PREPARED`` blocks are
made when it appears, not by the first ticks; a block handed back last is reused first, its memory the
likeliest in a cache) and, every ``batch`` ticks, tells the child writer which rows to take. When the
blocks run out (rows so large that a block holds a few, or a writer behind), the rows beyond the window
are handed over at once, and only then does it wait.
The child encodes them (a few numpy operations per channel and batch: poses are taken from the bus's
``<core>.<body>.pos`` / ``.quat`` columns), compresses and writes, on a core of its own and under an
interpreter lock of its own. Every writer call (schemas, channels, events) goes to the child the same
way, so the file holds the records in the order they were made. ``writer="thread"`` keeps the writer
in this process instead (on a thread; no child process, but encoding then competes with the
simulation for the interpreter lock). Figures: ``bench/logging_cost.py``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections import deque
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from ..kernel.errors import DynabrainError
from ..kernel.observers import Imagined, Observer, WorldEvent, WorldView
from .messages import Event, ImaginedRows, Layout, Metadata, Release, Span
from .meta import run_metadata
from .scene import SceneDrawing
from .schema import (
    IMAGINED,
    METADATA_NAME,
    BusCodec,
    FieldNumbers,
    bus_topic,
    event_bytes,
    event_level,
    foxglove_descriptor,
    imagined_frame,
    pose_columns,
    result_events,
)
from .sink import NOTHING_WRITTEN
from .sinks import ProcessSink, ThreadSink
from .write import COMPRESSIONS

_log = logging.getLogger("dynabrain.mcap")
BLOCK_BYTES = 2 << 20
"""Bus rows a block holds at most (bytes; and at most ``batch`` rows)."""
PREPARED = 2
"""Blocks made per bus layout when it appears (enough for a writer that keeps up); more are made while
the writer is behind, up to ``MAX_BLOCKS``."""
MAX_BLOCKS = 24
"""Blocks of rows per bus layout at most (48 MiB): when the writer is that far behind, the stepping
thread waits for it."""


class _Block:
    """Bus rows of consecutive ticks of one layout and epoch, in preallocated memory: row ``i`` is tick
    ``first + i``. Rows ``[0, sent)`` are handed to the writer; rows from ``cut`` on were discarded by a
    rollback. A block takes no more rows once ``sealed``; the writer hands it back to its pool after
    writing its last rows (``pool``)."""

    __slots__ = ("codec", "cut", "epoch", "extra", "first", "flat", "n", "pool", "rows", "scenes", "sealed", "sent",
                 "shared_extra", "shared_rows")

    def __init__(self, codec: BusCodec, capacity: int, extra: int, pool: deque, sink: ThreadSink | ProcessSink):
        self.codec, self.pool = codec, pool
        self.rows, self.shared_rows = sink.new_rows((capacity, codec.size))  # shared: the child writer maps it
        self.flat = memoryview(self.rows).cast("B").cast("d")  # the rows as one run of doubles (the hot path's copy)
        self.extra, self.shared_extra = sink.new_rows((capacity, extra)) if extra else (None, None)
        self.scenes: list[tuple[int, bytes]] = []

    def start(self, first: int, epoch: int) -> _Block:
        self.first, self.epoch, self.n, self.sent, self.cut, self.sealed = first, epoch, 0, 0, len(self.rows), False
        self.scenes = []
        return self


class McapLogger(Observer):
    """Records a world's run to an MCAP file. See the module docstring.

    ``decimate``: poses every that many ticks; ``scene_every``: the scene every that many ticks
    (default: one simulated second) and after each `make`; ``window``: ticks held back for rollbacks;
    ``batch``: ticks encoded and written together (at most ``flush_s / 2`` s after the first is due; fewer
    when a block of rows, ``BLOCK_BYTES``, holds fewer: 337 of the humanoid's; the writer's work per batch
    is mostly fixed, so for two cubes 1024 ticks cost it 2.95 us a tick where 256 cost 3.93, and the
    stepping thread 0.98 us where 256 cost 1.42);
    ``chunk_bytes``, ``chunk_s``, ``flush_s``, ``compression``, ``level``: a chunk's size at most (4 MB: each
    chunk repeats the schemas and channels of its messages, about 60 KB for the humanoid, which cost 6% of
    the data and, with the per-chunk work, 3 us a tick of the writer's 29 at 1 MB), the simulated time it
    spans at most, its age (wall time) at most, its compression (``"zstd"``, ``"lz4"`` or ``"none"``) and
    the zstd level (`logs.write`); ``writer``: ``"process"`` (a child
    process writes the file; the default) or ``"thread"`` (a thread of this process); ``ros2``: also
    ``/clock`` and ``/joint_states``, and ``/tf`` as ``tf2_msgs/msg/TFMessage``, in CDR with ``ros2msg``
    schemas (`logs.sink.Ros2Rows`), for rosbag2 users.
    """

    def __init__(self, path: str | os.PathLike[str], *, decimate: int = 1, scene_every: int | None = None,
                 window: int = 64, batch: int = 1024, chunk_bytes: int = 4 << 20, chunk_s: float = 1.0,
                 flush_s: float = 0.25, level: int = -1, compression: str = "zstd", writer: str = "process",
                 ros2: bool = False):
        for name, value, low in (("decimate", decimate, 1), ("window", window, 0), ("batch", batch, 1),
                                 ("scene_every", scene_every or 1, 1), ("chunk_bytes", chunk_bytes, 1)):
            if not isinstance(value, int) or value < low:
                raise DynabrainError(f"McapLogger: {name} must be an integer >= {low}, got {value!r}")
        if not isinstance(chunk_s, (int, float)) or isinstance(chunk_s, bool) or not 0 < chunk_s < 1e9:
            raise DynabrainError(f"McapLogger: chunk_s must be a positive number of seconds, got {chunk_s!r}")
        if writer not in ("process", "thread"):
            raise DynabrainError(f"McapLogger: writer must be 'process' or 'thread', got {writer!r}")
        self.path = os.fspath(path)
        self.writer = writer
        self.ros2 = bool(ros2)
        self.decimate, self.scene_every, self.window, self.batch = decimate, scene_every, window, batch
        self._due = batch
        if compression not in COMPRESSIONS:
            raise DynabrainError(f"McapLogger: compression must be one of {', '.join(map(repr, COMPRESSIONS))}, "
                                 f"got {compression!r}")
        self._writer_args = {"chunk_bytes": chunk_bytes, "chunk_ns": max(1, round(chunk_s * 1e9)), "flush_s": flush_s,
                             "level": level, "compression": compression}
        self._max_wait = flush_s / 2
        self._drained_at = time.monotonic()
        self._sink: ThreadSink | ProcessSink | None = None
        self._pending: deque[_Block] = deque()  # blocks with rows not handed to the writer yet, oldest first
        self._waiting = 0  # rows of ``_pending`` not handed to the writer
        self._block: _Block | None = None  # the block taking rows (None: the next row starts one)
        self._expect = -1  # the tick whose row the block takes next
        self._pools: dict[int, deque[_Block]] = {}
        self._numbers = FieldNumbers()
        self._codecs: dict[tuple, BusCodec] = {}
        self._pose_index: dict[int, tuple[np.ndarray, list[str]]] = {}
        self._codec: BusCodec | None = None
        self._missing: list[str] = []
        self._epoch = 0
        self._seq = 0
        self._dirty = True
        self._scene: SceneDrawing | None = None
        self._bodies: list[str] | None = None
        self._made: dict[int, int] = {}  # blocks made per layout
        self._next_scene = 0
        # the hot path (`on_tick`): ticks before `_fast_until` whose row goes right after the last one, from
        # the bus `_bus` (its memoryview `_bus_mv`), take the fast way; anything that may change that sets it -1
        self._fast_until = -1
        self._bus: np.ndarray | None = None
        self._bus_mv: memoryview | None = None
        self._written_max = -1
        self._compact = False
        self._restoring = False
        self._restored_snapshot: int | None = None
        self._failing: int | None = None
        self._lock: Any = None
        self._world: Any = None
        self.origin_ns = 0
        """The log time of tick 0 (ns since 1970): the wall-clock time at `attach`, less that tick's
        simulated time (see `logs.schema`)."""
        self.closed = False

    # -- attaching ------------------------------------------------------------------------------------
    def attach(self, world: Any, scenario: Any = None) -> McapLogger:
        """Start recording ``world`` (built from ``scenario``, when there is one) at its current tick."""
        with world.lock():
            view = WorldView(world)
            self._world, self._lock, self._dt = world, world.lock(), world.dt_ns
            if self.scene_every is None:
                self.scene_every = max(1, round(1e9 / self._dt))
            if view.core is not None:
                self._scene = SceneDrawing(view.core)
                self._bodies = list(view.core.bodies())
            descriptors = {cls.DESCRIPTOR.full_name: foxglove_descriptor(cls)
                           for cls in (FrameTransforms, SceneUpdate, Log)}
            sink = ProcessSink if self.writer == "process" else ThreadSink
            self._sink = sink(self.path, self._writer_args, self._dt, self.decimate, self._bodies, descriptors,
                              self.ros2)
            wall_ns = time.time_ns()  # the run starts now (the writer has started): log times count from here
            self.origin_ns = wall_ns - view.tick * self._dt
            try:
                settings = {"decimate": self.decimate, "scene_every": self.scene_every, "window": self.window,
                            "batch": self.batch, "writer": self.writer, **self._writer_args}
                if self.ros2:
                    settings["ros2"] = True
                meta = run_metadata(world, scenario, settings, wall_ns=wall_ns, origin_ns=self.origin_ns)
                self._sink.call(Metadata(METADATA_NAME, meta))
                self._refresh_layout(view)
                self._push(view, view.bus())
            except BaseException:
                self._sink.abort()
                raise
            world.observe(self)
        return self

    # -- observer hooks -------------------------------------------------------------------------------
    def on_tick(self, view: WorldView) -> None:
        """The hot path: copy the bus row into the block; everything else happens per batch."""
        tick, bus = view.tick, view.bus()
        if tick == self._expect and tick < self._fast_until and bus is self._bus:
            block = self._block
            n, width = block.n, len(bus)  # one memoryview copy: the row right after the last
            block.flat[n * width:n * width + width] = self._bus_mv
            block.n = n + 1
            self._expect = tick + 1
            self._waiting += 1
        else:
            if self.closed:
                return
            if self._dirty or bus.size != self._codec.size:
                self._refresh_layout(view)
            self._push(view, bus)
        waiting = self._waiting - self.window
        if waiting >= self._due or (waiting > 0 and time.monotonic() - self._drained_at >= self._max_wait):
            self._drain(waiting)

    def on_event(self, view: WorldView, event: WorldEvent) -> None:
        if self.closed:
            return
        self._fast_until = -1
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
        self._discard_after(last)
        if self._written_max > last:
            self._compact = True
        self._written_max = min(self._written_max, last)
        self._epoch += 1
        self._seal()
        detail = {"from_tick": from_tick, "to_tick": to, "cause": cause, "epoch": self._epoch}
        if cause == "restore" and self._restored_snapshot:
            detail["snapshot"] = self._restored_snapshot
        self._event("rollback", to, detail, "api")
        self._dirty = True
        self._next_scene = to
        self._fast_until = -1
        if cause == "restore":
            self._refresh_layout(view)
            self._push(view, view.bus())

    def on_imagined(self, view: WorldView, imagined: Imagined) -> None:
        """A branch the brain imagined: written at once to ``/imagined/<name>/<branch>/...`` (see
        `logs.schema`), with an ``imagined`` event; it never waits in the window, and rollbacks leave it."""
        if self.closed:
            return
        name, branch, start, ticks = imagined.name, imagined.branch, imagined.start_tick, imagined.ticks
        slots, offsets, at = [], {}, 0
        for signal, values in imagined.signals.items():
            slots.append((signal, values.shape[1:], imagined.units.get(signal, "")))
            offsets[signal] = (at, values.shape[1:])
            at += int(np.prod(values.shape[1:], dtype=np.int64))
        rows = np.concatenate([v.reshape(ticks, -1) for v in imagined.signals.values()], axis=1)
        bodies, cols = _imagined_poses(view.core.name if view.core is not None else None, offsets)
        scene = b""
        if bodies and self._scene is not None:
            frames = [imagined_frame(name, branch, b) for b in bodies]
            scene = self._scene.imagined(bodies, frames, self.origin_ns + (start + 1) * self._dt, ticks * self._dt)
        self._sink.call(ImaginedRows(name, branch, start, self._epoch, slots, rows, bodies, cols, scene))
        self._event("imagined", view.tick, {"name": name, "branch": branch, "start_tick": start, "ticks": ticks,
                                            "signals": list(imagined.signals), "topic": f"{IMAGINED}/{name}/{branch}",
                                            "bodies": bodies}, "api")

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
            for kind, detail in result_events(result):
                self._event(kind, int(result.ticks), detail, "log")

    def close(self) -> None:
        """Write what is waiting, the summary and the footer; rewrite the file if a rollback reached
        ticks already written, or messages were written out of log-time order (see the module
        docstring). Idempotent."""
        if self.closed or self._sink is None:
            return
        with self._lock:
            self.closed = True
            self._fast_until = -1
            with contextlib.suppress(ValueError):  # not observing any more (the caller took it off)
                self._world.unobserve(self)
            try:
                self._drain(self._waiting)
            finally:
                self._sink.finish()
        if self._compact or self._sink.stats.get("out_of_order"):
            from .recover import rewrite

            tmp = self.path + ".compacting"
            rewrite(self.path, tmp)
            os.replace(tmp, self.path)

    @property
    def stats(self) -> dict[str, float]:
        """What was written (messages, chunks, bytes; complete once closed), the rollback epoch, and the
        writer's CPU time (the child process's, or the writer thread's)."""
        done = self._sink.stats if self._sink is not None else NOTHING_WRITTEN
        return {**done, "epoch": self._epoch}

    # -- the stepping thread: rows into blocks ----------------------------------------------------------
    def _push(self, view: WorldView, bus: np.ndarray) -> None:
        """Any row the hot path does not take: a new block, the poses the bus lacks, the scene."""
        tick = view.tick
        block = self._block
        if block is None or tick != self._expect or block.n == len(block.rows) or block.codec is not self._codec:
            block = self._start_block(tick)
        row = block.n
        block.rows[row] = bus
        if self._missing and tick % self.decimate == 0:
            core = view.core
            block.extra[row] = np.concatenate([np.concatenate(core.body_pose(b)) for b in self._missing])
        if tick >= self._next_scene:
            if self._scene is not None:
                block.scenes.append((row, self._scene.encode(self.origin_ns + tick * self._dt)))
            self._next_scene = tick + self.scene_every
        block.n += 1
        self._expect = tick + 1
        self._waiting += 1
        if bus is not self._bus:
            self._bus, self._bus_mv = bus, memoryview(bus)
        # the ticks the hot path may take: up to the block's end or the next scene, while nothing else is due
        self._fast_until = -1 if self._dirty or self._missing else min(block.first + len(block.rows), self._next_scene)

    def _start_block(self, tick: int) -> _Block:
        self._seal()
        codec = self._codec
        pool = self._pools[codec.key]
        sink = self._sink
        sink.poll()
        capacity = self._capacity(codec)
        # at most MAX_BLOCKS, and at least the blocks the window's rows can span and one more
        most = max(MAX_BLOCKS, -(-self.window // capacity) + 2)
        while not pool and self._made.get(codec.key, 0) >= most:  # the writer is behind: wait for it
            waiting = self._waiting
            if waiting > self.window:  # hand over what waits beyond the window first, so that a block
                self._drain(waiting - self.window)  # comes back (rows so large that a block holds few)
                if self._waiting < waiting:
                    continue
            sink.wait()
        try:
            block = pool.pop()  # the block handed back last: its memory is the likeliest still in a cache
        except IndexError:
            block = _Block(codec, capacity, 7 * len(self._missing), pool, sink)
            self._made[codec.key] = self._made.get(codec.key, 0) + 1
        self._block = block.start(tick, self._epoch)
        self._pending.append(block)
        return block

    def _seal(self) -> None:
        """The block taking rows takes no more; one already written goes back (after the writer's jobs)."""
        block, self._block = self._block, None
        self._fast_until = -1
        if block is None:
            return
        block.sealed = True
        if block.sent == block.n:  # nothing of it waits (every older block was handed over before it)
            self._pending.remove(block)
            if block.n == 0:
                block.pool.append(block)
            else:
                self._sink.release(block)

    def _discard_after(self, last: int) -> None:
        """Mark the waiting rows of ticks after ``last`` discarded (newest first, as the rule says)."""
        for block in reversed(self._pending):
            lo, hi = block.sent, min(block.cut, block.n)
            if lo >= hi:
                continue
            if block.first + hi - 1 <= last:
                break
            block.cut = max(lo, last + 1 - block.first)
            if block.cut > lo:
                break

    def _refresh_layout(self, view: WorldView) -> None:
        slots = view.signal_slots()
        size = view.bus().size
        signature = (*sorted((n, o, tuple(sh), u) for n, (o, sh, u) in slots.items()), size)
        codec = self._codecs.get(signature)
        if codec is None:
            codec = BusCodec.from_view(slots, size, self._numbers, len(self._codecs) + 1)
            self._codecs[signature] = codec
            cols, missing = self._pose_index[codec.key] = self._pose_plan(view, codec)
            self._sink.call(Layout(codec.key, codec.metadata(), cols, missing, self._joints(view, slots)))
            detail: dict[str, Any] = {"layout": codec.key, "topic": bus_topic(codec.key), "signals": len(codec.slots),
                                      "values": size}
            if self._codec is not None:
                detail["added"] = sorted(set(codec.by_name) - set(self._codec.by_name))
                detail["removed"] = sorted(set(self._codec.by_name) - set(codec.by_name))
            self._event("layout", view.tick, detail, "log")
        self._codec = codec
        self._missing = self._pose_index[codec.key][1]
        self._dirty = False
        self._due = self._capacity(codec)  # rows handed over together: ``batch``, or the fewer a block holds
        if codec.key not in self._pools:
            self._prepare(codec)

    def _prepare(self, codec: BusCodec) -> None:
        """Make a new layout's first blocks now (``PREPARED``): making one maps and zeroes its memory, about
        1.3 ms for the humanoid's 1.6 MB, which the first ticks of a run would otherwise wait for."""
        pool = self._pools[codec.key] = deque()
        capacity = self._capacity(codec)
        for _ in range(PREPARED):
            pool.append(_Block(codec, capacity, 7 * len(self._missing), pool, self._sink))
        self._made[codec.key] = PREPARED

    def _capacity(self, codec: BusCodec) -> int:
        return max(1, min(self.batch, BLOCK_BYTES // (8 * codec.size)))

    def _joints(self, view: WorldView, slots: dict) -> tuple[tuple[str, ...], np.ndarray] | None:
        """For ROS 2 messages: the joints of ``/joint_states`` and their bus columns (q, qd[, effort])."""
        if not self.ros2 or view.core is None:
            return None
        from .ros2msgs import ros2_signals

        signals = ros2_signals(view.core.name, view.core.joints(), (), slots)
        groups = 3 if signals.effort else 2
        cols = [slots[name][0] for name in signals.names]
        return signals.joints, np.array(cols, dtype=np.intp).reshape(groups, len(signals.joints))

    def _pose_plan(self, view: WorldView, codec: BusCodec) -> tuple[np.ndarray, list[str]]:
        if self._bodies is None:
            return np.zeros((0, 7), dtype=np.intp), []
        return pose_columns(view.core.name, self._bodies, codec)

    def _drain(self, n: int) -> None:
        """Hand the ``n`` oldest waiting rows to the writer, in one call."""
        self._drained_at = time.monotonic()
        parts: list[Span | Release] = []
        while n > 0 and self._pending:
            block = self._pending[0]
            a = block.sent
            b = min(block.n, a + n)
            if b > a:
                for lo, hi, discarded in ((a, min(b, block.cut), False), (max(a, block.cut), b, True)):
                    if hi > lo:
                        parts.append(Span(block, lo, hi, discarded))
                        if not discarded:
                            self._written_max = max(self._written_max, block.first + hi - 1)
                block.sent = b
                n -= b - a
                self._waiting -= b - a
            if block.sent < block.n or not block.sealed:
                break
            self._pending.popleft()
            parts.append(Release(block))  # its last rows are written: back to its pool
        if parts:
            self._sink.rows(parts)

    def _event(self, kind: str, tick: int, detail: dict, source: str) -> None:
        self._seq += 1
        body = {"seq": self._seq, "tick": tick, "time": tick * self._dt / 1e9, "epoch": self._epoch, "kind": kind,
                "source": source, "detail": detail}
        self._sink.call(Event(tick * self._dt, kind, event_level(kind, detail), event_bytes(body).decode(),
                              self._epoch))


def _imagined_poses(core: str | None, offsets: dict[str, tuple[int, tuple[int, ...]]]) -> tuple[list[str], np.ndarray]:
    """The bodies whose ``<core>.<body>.pos`` (3) and ``.quat`` (4) are among an imagined branch's
    signals (``offsets``: signal -> its first column and shape), and their 7 columns (x y z qw qx qy qz)."""
    bodies, cols = [], []
    for signal, (pos, shape) in offsets.items():
        if core is None or not signal.startswith(core + ".") or not signal.endswith(".pos") or shape != (3,):
            continue
        body = signal[len(core) + 1:-len(".pos")]
        quat, quat_shape = offsets.get(f"{core}.{body}.quat", (0, ()))
        if quat_shape == (4,):
            bodies.append(body)
            cols.append([pos, pos + 1, pos + 2, quat, quat + 1, quat + 2, quat + 3])
    return bodies, np.array(cols, dtype=np.intp).reshape(-1, 7)
