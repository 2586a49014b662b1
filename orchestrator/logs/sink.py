"""Where an MCAP log is encoded and written: in a child process (the default) or on a thread.

The logger (`logs.logger`) runs on the world's stepping thread: it copies bus rows into blocks and
decides what is written when. A *sink* does the rest: it registers channels, encodes batches of rows
into ``/bus``, ``/tf`` and ``/scene`` messages (and, when asked, ROS 2 ones: `Ros2Rows`) and imagined
branches into ``/imagined/...`` ones, writes events and metadata, and hands chunks to the `McapWriter`.
Every sink call arrives in the order the logger made it.

Log-time order. A batch of rows goes to the writer as one group (`McapWriter.add_group`: its bus,
pose and scene messages merged by time), with the events and imagined messages whose time has come.
Those arrive before the rows of their tick (rows wait in the logger for a batch, and an imagined
branch lies in the future), so the sink holds them until the rows reach their time, then merges them
in; what is still held when the log finishes is written then, in order. At equal times the run's
messages come first. Only a rollback (ticks produced again) or a branch imagined from a past tick
writes messages below the latest log time (`McapWriter.out_of_order` counts them; the logger then
puts the file in order when it closes).

`logs.sinks.ProcessSink` (the default) runs the sink in a child process (``python -m
dynabrain.orchestrator.logs.sink``; it starts in about 0.15 s, and `attach` waits for it). Rows
travel through shared memory (each block of rows is a file in ``/dev/shm``, or in the temporary
folder when that is missing or full, mapped by both processes), calls through a pipe (each message a
named type of `logs.messages`); the child acknowledges each batch so the block can take rows again.
Encoding and compression then cost the simulation only the row copies: on a thread of the
simulation's process they hold its interpreter lock part of the time, and logging the humanoid cost
about 45% of its step that way (``bench/logging_cost.py``). If the simulation's process dies, the
child sees the pipe close and finishes the file (summary and footer): nothing handed over is lost. A
shared file's name is removed as soon as the child has mapped it (files of processes killed before
that are removed by the next log started: `logs.shared_rows`). `logs.sinks.ThreadSink` runs the same
sink on the writer's thread in this process (``McapLogger(writer="thread")``).
"""

from __future__ import annotations

import contextlib
import mmap
import signal
import sys
import time
from collections.abc import Callable, Hashable, Mapping, Sequence
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError
from .messages import (
    Abort,
    Call,
    Done,
    Event,
    Failed,
    Finish,
    Finished,
    ImaginedRows,
    Layout,
    Metadata,
    Open,
    Ready,
    Rows,
)
from .schema import (
    DISCARDED,
    IMAGINED,
    METADATA_NAME,
    TOPIC_BUS,
    TOPIC_EVENTS,
    TOPIC_SCENE,
    TOPIC_TF,
    BusCodec,
    FieldNumbers,
    PoseCodec,
    Slot,
    bus_topic,
    imagined_frame,
    log_message,
)
from .shared_rows import mapped
from .write import McapWriter, Part

START_TIMEOUT_S = 60.0
"""How long the child writer may take to start (it imports numpy; on a busy machine that is slow)."""
FINISH_TIMEOUT_S = 300.0
"""How long closing waits for a child writer to write what it was handed."""
NOTHING_WRITTEN = {"messages": 0, "chunks": 0, "bytes": 0, "writer_cpu_s": 0.0, "encode_cpu_s": 0.0,
                   "compress_cpu_s": 0.0, "out_of_order": 0}
"""A log's statistics (`LogSink.finish`): ``writer_cpu_s`` is the writer's CPU time (the child process's
whole, or the writer thread's), ``encode_cpu_s`` and ``compress_cpu_s`` the parts of it spent encoding
rows into messages and compressing chunks."""
LOG_SCHEMA = "foxglove.Log"


class _Held:
    """Messages of one channel held until the run's rows reach their (simulated) times: ``data`` is
    (n, length) uint8, the messages from ``at`` on are still held."""

    __slots__ = ("at", "channel", "data", "epochs", "times")

    def __init__(self, channel: int, times: np.ndarray, epochs: np.ndarray, data: np.ndarray):
        self.channel, self.times, self.epochs, self.data, self.at = channel, times, epochs, data, 0


class LogSink:
    """The writing side of a log (see the module docstring): runs where the `McapWriter` is."""

    def __init__(self, path: str, writer_args: Mapping[str, Any], dt_ns: int, decimate: int,
                 bodies: Sequence[str] | None, descriptors: Mapping[str, bytes], ros2: bool = False):
        self.writer = McapWriter(path, **writer_args)  # no profile: dynabrain is no well-known MCAP profile
        self.dt, self.decimate = dt_ns, decimate
        self.origin = 0
        """The log time of tick 0: the ``time_origin_ns`` of the ``dynabrain`` metadata, written first."""
        self.held: list[_Held] = []
        self.topic_schemas: dict[str, int] = {}  # one schema per topic
        self.poses = PoseCodec(bodies) if bodies is not None else None
        self.descriptors = dict(descriptors)  # Foxglove schema name -> serialized FileDescriptorSet
        self.layouts: dict[int, tuple[BusCodec, np.ndarray, list[str]]] = {}
        self.channels: dict[tuple[str, Hashable], int] = {}
        self.schema_ids: dict[int | str | tuple[str, int], int] = {}
        self.imagined_codecs: dict[tuple, BusCodec] = {}  # by the signals' (name, shape, unit)
        self.imagined_poses: dict[tuple[str, ...], PoseCodec] = {}
        self.ros2 = Ros2Rows(self) if ros2 else None
        self.encode_cpu_s = 0.0
        """CPU time spent in `rows` (encoding and adding messages; the chunks it finishes are compressed on
        the writer's thread, `McapWriter.compress_cpu_s`, which is part of this with ``writer="thread"``,
        where `rows` runs on that thread)."""
        self.events_channel()

    # -- calls ------------------------------------------------------------------------------------------
    def metadata(self, name: str, values: Mapping[str, str]) -> None:
        if name == METADATA_NAME and "time_origin_ns" in values:
            self.origin = int(values["time_origin_ns"])
        self.writer.add_metadata(name, values)

    def layout(self, key: int, meta: Mapping[str, str], cols: np.ndarray, missing: list[str],
               joints: tuple[tuple[str, ...], np.ndarray] | None = None) -> None:
        """A bus layout (a codec, by its channel metadata) and where its poses are (and, for ROS 2
        messages, its joints). The codecs encode a row once now, so that their first real batch does not
        pay for the first use of their code."""
        codec = BusCodec.from_metadata(meta)
        self.layouts[key] = (codec, cols, missing)
        if self.ros2 is not None:
            self.ros2.joints[key] = joints
        row = np.zeros((1, codec.size))
        codec.encode(row, np.zeros(1, np.int64), np.zeros(1, np.int64), self.dt)
        if self.poses is not None:
            self.poses.encode(np.zeros((1, len(self.poses.bodies), 3)), np.zeros((1, len(self.poses.bodies), 4)),
                              np.zeros(1, np.int64))

    def event(self, time_ns: int, kind: str, level: int, text: str, epoch: int) -> None:
        """An event, as ``foxglove.Log``: held until the rows reach its time."""
        data = np.frombuffer(log_message(self.origin + time_ns, level, text, kind), dtype=np.uint8)
        self._hold(self.events_channel(), np.array([time_ns], np.int64), np.array([epoch], np.int64), data[None, :])

    def rows(self, key: int, rows: np.ndarray, extra: np.ndarray | None, first: int, epoch: int,
             discarded: bool, scenes: Sequence[tuple[int, bytes]]) -> None:
        """Encode rows of consecutive ticks (the first is ``first``; one layout, epoch and fate) into
        ``/bus``, ``/tf`` and ``/scene`` messages, and write them, with the held messages whose time has
        come, as one group merged by log time."""
        t0 = time.thread_time()
        try:
            self._rows(key, rows, extra, first, epoch, discarded, scenes)
        finally:
            self.encode_cpu_s += time.thread_time() - t0

    def _rows(self, key: int, rows: np.ndarray, extra: np.ndarray | None, first: int, epoch: int,
              discarded: bool, scenes: Sequence[tuple[int, bytes]]) -> None:
        codec, cols, missing = self.layouts[key]
        prefix, dt, origin = DISCARDED if discarded else "", self.dt, self.origin
        n = len(rows)
        ticks = np.arange(first, first + n, dtype=np.int64)
        epochs = np.full(n, epoch, dtype=np.int64)
        t_ns = ticks * dt
        log = t_ns + origin

        def bus(out: np.ndarray, part: slice) -> None:
            codec.encode(rows[part], ticks[part], epochs[part], dt, out=out)

        parts = [Part(self.bus_channel(codec, prefix), log, epochs, codec.length, bus, t_ns)]
        due = np.flatnonzero(ticks % self.decimate == 0)
        pose = None
        if self.poses is not None and len(due):
            ext = rows if len(due) == n else rows[due]
            if missing:
                ext = np.concatenate([ext, extra[due]], axis=1)
            pose, stamps = ext[:, cols], log[due]
            poses = self.poses

            def fill(out: np.ndarray, part: slice) -> None:
                poses.encode(pose[part, :, :3], pose[part, :, 3:], stamps[part], out=out)

            if self.ros2 is None:
                parts.append(Part(self.proto_channel(prefix + TOPIC_TF, "foxglove.FrameTransforms"), stamps,
                                  epochs[due], poses.length, fill, t_ns[due]))
        if self.ros2 is not None and len(due):
            parts += self.ros2.parts(key, prefix, rows[due], pose, t_ns[due], epochs[due])
        for row, scene in scenes:
            parts.append(_single(self.proto_channel(prefix + TOPIC_SCENE, "foxglove.SceneUpdate"), int(t_ns[row]),
                                 origin, scene, epoch))
        self.writer.add_group(parts + self._due(int(t_ns[-1])))

    def _hold(self, channel: int, times: np.ndarray, epochs: np.ndarray, data: np.ndarray) -> None:
        self.held.append(_Held(channel, times, epochs, data))

    def _due(self, until_ns: int | None) -> list[Part]:
        """The held messages of simulated times up to ``until_ns`` (None: all), as parts; no longer held."""
        parts, still = [], []
        for item in self.held:
            end = len(item.times) if until_ns is None else int(np.searchsorted(item.times, until_ns, "right"))
            if end > item.at:
                at, data = item.at, item.data

                def fill(out: np.ndarray, part: slice, data: np.ndarray = data, at: int = at) -> None:
                    out[:] = data[at + part.start:at + part.stop]

                times = item.times[at:end]
                parts.append(Part(item.channel, times + self.origin, item.epochs[at:end], data.shape[1], fill, times))
                item.at = end
            if item.at < len(item.times):
                still.append(item)
        self.held = still
        return parts

    def imagined(self, name: str, branch: int, start_tick: int, epoch: int, slots: list[tuple[str, tuple, str]],
                 values: np.ndarray, bodies: list[str], cols: np.ndarray, scene: bytes) -> None:
        """A branch the brain imagined (`messages.ImaginedRows`): its signals to ``/imagined/<name>/<branch>/bus``
        (one message per tick, a schema of their own), the poses of its bodies to ``.../tf`` in frames of
        their own (`schema.imagined_frame`), their drawing to ``.../scene``; at the branch's own ticks,
        held until the run's rows reach them (see the module docstring)."""
        codec = self._imagined_codec(slots)
        prefix, dt = f"{IMAGINED}/{name}/{branch}", self.dt
        n = len(values)
        ticks = np.arange(start_tick + 1, start_tick + 1 + n, dtype=np.int64)
        epochs = np.full(n, epoch, dtype=np.int64)
        t_ns = ticks * dt
        rows = np.ascontiguousarray(values, dtype=np.float64)
        meta = {**codec.metadata(), "imagined": name, "branch": str(branch), "start_tick": str(start_tick)}
        self._hold(self.imagined_channel(prefix + TOPIC_BUS, codec, meta), t_ns, epochs,
                   codec.encode(rows, ticks, epochs, dt).copy())
        if bodies:
            frames = tuple(imagined_frame(name, branch, b) for b in bodies)
            poses = self.imagined_poses.get(frames)
            if poses is None:
                poses = self.imagined_poses[frames] = PoseCodec(frames)
            pose = rows[:, np.asarray(cols, dtype=np.intp)]
            self._hold(self.proto_channel(prefix + TOPIC_TF, "foxglove.FrameTransforms"), t_ns, epochs,
                       poses.encode(pose[:, :, :3], pose[:, :, 3:], t_ns + self.origin).copy())
        if scene:
            self._hold(self.proto_channel(prefix + TOPIC_SCENE, "foxglove.SceneUpdate"), t_ns[:1], epochs[:1],
                       np.frombuffer(scene, dtype=np.uint8)[None, :])

    def _imagined_codec(self, slots: list[tuple[str, tuple, str]]) -> BusCodec:
        key = tuple((n, tuple(sh), u) for n, sh, u in slots)
        codec = self.imagined_codecs.get(key)
        if codec is None:
            laid, at = [], 0
            for n, sh, u in key:
                laid.append(Slot(n, at, sh, u))
                at += laid[-1].size
            codec = BusCodec(laid, FieldNumbers(), at, len(self.imagined_codecs) + 1, kind="imagined")
            self.imagined_codecs[key] = codec
        return codec

    def apply(self, call: Call) -> None:
        """Make one of the logger's calls: the method of the message's name, with its fields."""
        method = _CALLS.get(type(call))
        if method is None:
            raise DynabrainError(f"the log writer got {type(call).__name__}, which is no writer call")
        method(self, *call)

    def finish(self) -> dict[str, float]:
        """Write the summary and footer; what was written."""
        w = self.writer
        w.call(lambda: w.add_group(self._due(None)))  # after the jobs handed over before (`ThreadSink`)
        w.finish()
        return {"messages": w.messages, "chunks": w.chunks, "bytes": w.bytes_written, "writer_cpu_s": w.thread_cpu_s,
                "encode_cpu_s": self.encode_cpu_s, "compress_cpu_s": w.compress_cpu_s, "out_of_order": w.out_of_order}

    # -- channels ---------------------------------------------------------------------------------------
    def _channel(self, topic: str, make: Callable[[], int], key: Hashable = 0) -> int:
        cid = self.channels.get((topic, key))
        if cid is None:
            cid = self.channels[(topic, key)] = make()
        return cid

    def _add_channel(self, topic: str, sid: int, meta: Mapping[str, str] | None = None,
                     encoding: str = "protobuf") -> int:
        """A channel on ``topic`` with schema ``sid``: a topic keeps one schema (a second one is a bug)."""
        known = self.topic_schemas.setdefault(topic, sid)
        if known != sid:
            raise DynabrainError(f"the log writer put two schemas on topic {topic} ({known} and {sid})")
        return self.writer.add_channel(topic, encoding, sid, meta)

    def _schema(self, key: Hashable, name: str, data: Callable[[], bytes], encoding: str = "protobuf") -> int:
        sid = self.schema_ids.get(key)
        if sid is None:
            sid = self.schema_ids[key] = self.writer.add_schema(name, encoding, data())
        return sid

    def events_channel(self) -> int:
        def make() -> int:
            return self._add_channel(TOPIC_EVENTS, self._schema(LOG_SCHEMA, LOG_SCHEMA,
                                                                lambda: self.descriptors[LOG_SCHEMA]))

        return self._channel(TOPIC_EVENTS, make)

    def bus_channel(self, codec: BusCodec, prefix: str) -> int:
        topic = prefix + bus_topic(codec.key)

        def make() -> int:
            return self._add_channel(topic, self._schema(codec.key, codec.schema_name, codec.descriptor),
                                     codec.metadata())

        return self._channel(topic, make, codec.key)

    def imagined_channel(self, topic: str, codec: BusCodec, meta: dict[str, str]) -> int:
        sid = self._schema(("imagined", codec.key), codec.schema_name, codec.descriptor)
        if self.topic_schemas.get(topic, sid) != sid:  # these signals differ from the first branch's here
            topic = f"{topic}/layout{codec.key}"

        def make() -> int:
            return self._add_channel(topic, sid, meta)

        return self._channel(topic, make, ("imagined", codec.key, meta["start_tick"]))

    def proto_channel(self, topic: str, schema: str) -> int:
        def make() -> int:
            return self._add_channel(topic, self._schema(schema, schema, lambda: self.descriptors[schema]))

        return self._channel(topic, make)

    def ros2_channel(self, topic: str, msgtype: str, msgdef: Callable[[], bytes]) -> int:
        """A channel of ROS 2 messages: CDR, its schema the ``ros2msg`` definition of ``msgtype``."""
        def make() -> int:
            return self._add_channel(topic, self._schema(("ros2", msgtype), msgtype, msgdef, "ros2msg"),
                                     encoding="cdr")

        return self._channel(topic, make)


class Ros2Rows:
    """A log's ROS 2 messages (``McapLogger(ros2=True)``, `logs.ros2msgs`): at each tick that has poses (every
    ``decimate``), ``/clock``, ``/joint_states`` and ``/tf`` (``tf2_msgs/msg/TFMessage`` in place of
    ``foxglove.FrameTransforms``), each encoded by rosbags, stamped with the simulated time (the ``/clock``
    they go with), with the run's log times, epochs and ``/discarded/...`` topics like every other channel."""

    def __init__(self, sink: LogSink):
        from .ros2msgs import Codec

        self.sink, self.codec = sink, Codec()
        self.joints: dict[int, tuple[tuple[str, ...], np.ndarray] | None] = {}

    def parts(self, key: int, prefix: str, rows: np.ndarray, pose: np.ndarray | None, t_ns: np.ndarray,
              epochs: np.ndarray) -> list[Part]:
        from .ros2msgs import CLOCK, JOINT_STATE, TF

        codec, sink = self.codec, self.sink
        stamps = [codec.stamp(int(t)) for t in t_ns]
        log = t_ns + sink.origin
        out = _sized(sink.ros2_channel(prefix + "/clock", CLOCK, lambda: codec.msgdef(CLOCK)),
                     [codec.encode(codec.clock(s)) for s in stamps], log, epochs, t_ns)
        joints = self.joints.get(key)
        if joints is not None and joints[0]:
            names, cols = joints
            q, qd = rows[:, cols[0]], rows[:, cols[1]]
            effort = rows[:, cols[2]] if len(cols) > 2 else np.zeros((len(rows), 0))
            data = [codec.encode(codec.joint_state(s, names, q[i], qd[i], effort[i])) for i, s in enumerate(stamps)]
            out += _sized(sink.ros2_channel(prefix + "/joint_states", JOINT_STATE, lambda: codec.msgdef(JOINT_STATE)),
                          data, log, epochs, t_ns)
        if pose is not None and sink.poses is not None and sink.poses.bodies:
            bodies = sink.poses.bodies
            data = [codec.encode(codec.tf_message(s, bodies, pose[i, :, :3], pose[i, :, 3:]))
                    for i, s in enumerate(stamps)]
            out += _sized(sink.ros2_channel(prefix + TOPIC_TF, TF, lambda: codec.msgdef(TF)), data, log, epochs, t_ns)
        return out


def _sized(channel: int, data: list[bytes], log_times: np.ndarray, epochs: np.ndarray,
           publish_times: np.ndarray) -> list[Part]:
    """Messages of one channel as `Part`s, one per message size (a part's messages have one size)."""
    sizes = np.array([len(d) for d in data])
    parts = []
    for size in np.unique(sizes):
        at = np.flatnonzero(sizes == size)
        block = np.frombuffer(b"".join(data[i] for i in at), dtype=np.uint8).reshape(len(at), int(size))

        def fill(out: np.ndarray, part: slice, block: np.ndarray = block) -> None:
            out[:] = block[part]

        parts.append(Part(channel, log_times[at], epochs[at], int(size), fill, publish_times[at]))
    return parts


def _single(channel: int, time_ns: int, origin_ns: int, data: bytes, epoch: int) -> Part:
    """One message as a `Part`, at simulated time ``time_ns``."""
    def fill(out: np.ndarray, part: slice) -> None:
        out[0] = np.frombuffer(data, dtype=np.uint8)

    return Part(channel, np.array([origin_ns + time_ns], np.uint64), np.array([epoch]), len(data), fill,
                np.array([time_ns], np.uint64))


_CALLS: dict[type, Callable[..., None]] = {Metadata: LogSink.metadata, Layout: LogSink.layout, Event: LogSink.event,
                                           ImaginedRows: LogSink.imagined}
"""Each writer call's method: its message's fields are the method's arguments, in order."""


def _serve(conn: Connection) -> None:
    """The child writer: open the log as told, take calls until ``finish``. When the simulation's
    process is gone (its end of the pipe closed, maybe in the middle of a message, or an answer to it
    cannot be sent), finish the file with what arrived."""
    try:
        opened: Open = conn.recv()
        sink = LogSink(*opened)
        sink.writer.warm_up()
    except EOFError:
        return
    except BaseException as exc:  # reported to the parent, which raises it
        _tell(conn, Failed(_message(exc)))
        return
    maps: dict[str, tuple[mmap.mmap, np.ndarray]] = {}
    try:
        if _tell(conn, Ready()):
            _take_calls(conn, sink, opened.path, maps)
    finally:
        for mm, _array in maps.values():
            with contextlib.suppress(Exception):
                mm.close()


def _take_calls(conn: Connection, sink: LogSink, path: str, maps: dict[str, tuple[mmap.mmap, np.ndarray]]) -> None:
    failed, done, gone = False, 0, False  # gone: answers cannot be sent; the calls still in the pipe are taken
    cpu0 = time.process_time()
    while True:
        try:
            message = conn.recv()
        except Exception:  # the simulation's process is gone
            break
        kind = type(message)
        if kind is Finish:
            try:
                stats = sink.finish()
                stats["writer_cpu_s"] = time.process_time() - cpu0
                _tell(conn, Finished(stats))
            except BaseException as exc:
                _tell(conn, Failed(_message(exc)))
            return
        if kind is Abort:
            with contextlib.suppress(BaseException):
                sink.writer.close()
            return
        answer: Done | Failed | None = None
        try:
            if kind is Rows:
                done += 1
                if not failed:
                    for part in message.parts:
                        lo, hi, extra = part.lo, part.hi, part.extra
                        rows = mapped(part.rows, maps)[lo:hi]
                        more = None if extra is None else mapped(extra, maps)[lo:hi]
                        sink.rows(part.key, rows, more, part.first + lo, part.epoch, part.discarded, part.scenes)
                answer = Done(done)
            elif not failed:
                sink.apply(message)
        except BaseException as exc:  # the parent raises it at its next call
            failed = True
            answer = Failed(f"writing the log {path} failed: {_message(exc)}")
        if answer is not None and not gone:
            gone = not _tell(conn, answer)
    with contextlib.suppress(BaseException):  # keep what it handed over
        sink.finish()


def _tell(conn: Connection, message: Ready | Done | Failed | Finished) -> bool:
    """Send to the simulation's process; False when it is gone."""
    try:
        conn.send(message)
    except OSError:
        return False
    return True


def reply_reason(reply: Any) -> str:
    """Why the child did not answer as asked (`Failed`, or a message it should not have sent)."""
    return reply.reason if type(reply) is Failed else f"the log writer process answered {reply!r}"


def _message(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, DynabrainError) else f"{type(exc).__name__}: {exc}"


if __name__ == "__main__":
    # Ctrl-C in a terminal, or a stop sent to the whole process group, is for the simulation: it
    # closes its log, or dies and closes the pipe; either way this process then finishes the file
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _serve(Connection(int(sys.argv[1])))
