"""What a dynabrain log holds, channel by channel, and the codecs of its hot channels.

Times. A message's MCAP ``log_time`` is the run's wall-clock start plus its simulated time:
``time_origin_ns + tick * step`` ns, where ``time_origin_ns`` (in the ``dynabrain`` metadata) is the
wall-clock time (ns since 1970, UTC) at which the logger was attached, less the simulated time of that
tick; its ``publish_time`` is the simulated time itself, ``tick * step`` ns from tick 0; the ``/bus``
messages also carry ``tick`` and ``time`` (simulated seconds), the events their tick and time. So
Foxglove shows the run at the date it ran, and the simulated time stays exact. The timestamps inside
Foxglove messages (poses, scene entities, logs) are log times too, so that Foxglove's transform lookups
and lifetimes line up with its timeline. A message's ``sequence`` is the *epoch*: how many rollbacks
the world had gone through when it was produced. Messages are in log-time order in the file (see
`logs.write`); a log with rollbacks is put in that order when it is closed (`logs.logger`).

Topics, one schema each (what the MCAP spec expects of a topic):

- ``/bus``: the whole signal bus, one protobuf message per tick (`BusCodec`). Its schema is made from
  the bus layout: fields ``tick``, ``epoch``, ``time`` and one field per signal, named after it
  (``core.aa.pos`` is ``core__aa__pos``; its JSON name is the signal's own name), so Foxglove plots
  ``/bus.core__aa__pos[2]``. The schema is a plain FileDescriptorSet that strict readers (the ``mcap``
  CLI's ``cat --json``) decode: the units are in the channel's metadata (``units``: signal -> unit), not
  in comments. A block port whose rows all have names of
  their own is written as those rows, so every bus value is written once. When modules arrive or
  leave, the new layout is a new schema, so it goes to a topic of its own: layout ``k`` (counted in
  the log, from 1) on ``/bus/layout<k>`` (`bus_topic`; the first layout stays on ``/bus``, and a
  layout the world comes back to goes back to its topic). A signal keeps its field number for the
  whole file, so one layout's schema still decodes another's messages (fields it lacks are skipped).
  The channel's metadata holds the layout (signal -> offset, shape, unit) that turns a message back
  into the bus array; a ``layout`` event names the topic of each new layout.
- ``/tf``: body poses as ``foxglove.FrameTransforms`` (parent ``world``, child the body's name).
- with ROS 2 messages (``McapLogger(ros2=True)``, ``run --ros2-schemas``; `logs.sink.Ros2Rows`): ``/tf`` as
  ``tf2_msgs/msg/TFMessage`` instead, ``/clock`` (``rosgraph_msgs/msg/Clock``) and ``/joint_states``
  (``sensor_msgs/msg/JointState``), in CDR with ``ros2msg`` schemas (`logs.ros2msgs`), header stamps and the
  clock in simulated time, at the ticks that have poses.
- ``/scene``: the bodies' geometry as ``foxglove.SceneUpdate`` (see `logs.scene`).
- ``/events``: events (edits, parameter changes, rollbacks, errors, expectation results) as
  ``foxglove.Log`` (what Foxglove's Log panel shows): ``name`` is the event's kind, ``level`` says how
  notable it is (`event_level`), ``message`` is the whole event as JSON (``seq``, ``tick``, ``time``,
  ``epoch``, ``kind``, ``source``, ``detail``), ``timestamp`` its log time. Logs written before kept
  the same JSON as messages of a JSON schema ``dynabrain.Event``; `logs.read` reads both.
- ``/discarded/bus`` (and ``/discarded/bus/layout<k>``), ``/discarded/tf``, ``/discarded/scene``: ticks
  a rollback discarded.
- ``/imagined/<name>/<branch>/...``: futures the brain imagined and asked to keep (`World.imagine`; a
  batch's branches with ``BatchResult.imagine``, a plan with ``Plan.imagine``), each branch on topics of
  its own, at its own future ticks (the message after tick ``start + k + 1`` at that tick's time), so
  Foxglove plays the prediction beside what happened. ``.../bus``: the signals recorded, one message per
  tick, a schema of their own (``dynabrain.imagined<n>.Bus``, made as ``/bus``'s is; a later branch of
  the same name and number with other signals goes to ``.../bus/layout<n>``); the channel's
  metadata gives the layout, ``imagined`` (the name), ``branch`` and ``start_tick``. ``.../tf``: when the
  signals hold a body's ``<core>.<body>.pos`` and ``.quat``, its poses as ``foxglove.FrameTransforms`` in
  a frame of its own, ``imagined/<name>/<branch>/<body>`` (parent ``world``); ``.../scene``: those bodies
  drawn translucent in those frames, once, for the branch's duration. An ``imagined`` event on
  ``/events`` says when the brain imagined it. An imagined branch is not a discarded future of the run:
  rollbacks do not move it to ``/discarded/...``, `logs.read` leaves it out of the run, and ``replay
  --verify`` does not compare it; it stays in the log as it was written.

The hot codecs write messages of a fixed size per layout, so a batch of ticks encodes with a few
numpy operations: fixed64 and double fields, packed repeated doubles, and in the pose messages
timestamps whose varints are padded to five bytes (valid protobuf: parsers accept non-minimal varints;
the tests decode them with the foxglove schema package and the mcap package's protobuf decoder).
"""

from __future__ import annotations

import functools
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2

TOPIC_BUS, TOPIC_TF, TOPIC_SCENE, TOPIC_EVENTS = "/bus", "/tf", "/scene", "/events"
DISCARDED = "/discarded"
IMAGINED = "/imagined"
FORMAT = "dynabrain-log/1"
METADATA_NAME = "dynabrain"
FIRST_SIGNAL_FIELD = 16
_HEADER_FIELDS = (("tick", 1, 0x09), ("epoch", 2, 0x11), ("time", 3, 0x19))
HEADER_BYTES = 27

LEVELS = {"debug": 1, "info": 2, "warning": 3, "error": 4}
"""``foxglove.Log`` levels (its ``Level`` enum)."""


def bus_topic(layout: int) -> str:
    """The topic of bus layout ``layout`` (see the module docstring): one schema per topic."""
    return TOPIC_BUS if layout == 1 else f"{TOPIC_BUS}/layout{layout}"


def bus_family(topic: str) -> str:
    """``/bus/layout3`` -> ``/bus`` (and ``/discarded/bus/layout3`` -> ``/discarded/bus``): the topic
    whose ticks a layout's messages share."""
    head, _, last = topic.rpartition("/")
    return head if last.startswith("layout") and last[6:].isdigit() and head.endswith(TOPIC_BUS) else topic


def event_level(kind: str, detail: dict) -> int:
    """How notable an event is, as a ``foxglove.Log`` level: errors and failed runs ERROR, rollbacks and
    failed expectations WARNING, the logger's own bookkeeping (layouts) DEBUG, the rest INFO."""
    if kind == "error" or (kind == "run_end" and (detail.get("error") or not detail.get("ok", True))):
        return LEVELS["error"]
    if kind == "rollback" or (kind == "expect" and not detail.get("passed", True)):
        return LEVELS["warning"]
    return LEVELS["debug"] if kind == "layout" else LEVELS["info"]


RUN_KINDS = ("run_start", "expect", "run_end")
"""The events that say how a run went: its start (a live view's), its expectation results, its end. A live
view keeps them for a client that connects late, however many events came between (`logs.live`)."""


def result_events(result: Any) -> list[tuple[str, dict]]:
    """The events of a run's result (a `RunResult`): one ``expect`` per expectation, then ``run_end``, as
    (kind, detail); a log (`McapLogger.log_result`) and a live view (`LiveView.log_result`) send the same."""
    out: list[tuple[str, dict]] = []
    for exp in result.expectations:  # at the run's end, when they are known (their ticks are in them)
        out.append(("expect", {"name": exp.label, "that": exp.that, "passed": bool(exp.passed), "detail": exp.detail,
                               "from_tick": exp.start, "to_tick": exp.end}))
    out.append(("run_end", {"ticks": int(result.ticks), "sim_time": result.sim_time, "wall_time": result.wall_time,
                            "error": result.error, "ok": result.ok, "ended": getattr(result, "ended", None)}))
    return out


def log_message(time_ns: int, level: int, text: str, name: str) -> bytes:
    """A ``foxglove.Log`` message (timestamp, level, message, name), encoded."""
    stamp = b"\x08" + varint(time_ns // 1_000_000_000) + b"\x10" + varint(time_ns % 1_000_000_000)
    raw, label = text.encode(), name.encode()
    return (b"\x0a" + varint(len(stamp)) + stamp + b"\x10" + varint(level) + b"\x1a" + varint(len(raw)) + raw
            + b"\x22" + varint(len(label)) + label)


def imagined_frame(name: str, branch: int, body: str) -> str:
    """The frame of a body in an imagined branch (``/imagined/<name>/<branch>/tf``): a frame of its own,
    so that Foxglove draws the prediction beside the body, not in its place."""
    return f"imagined/{name}/{branch}/{body}"


def varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def field_name(signal: str) -> str:
    """A protobuf field name for a signal: dots become ``__``, other characters that a protobuf identifier
    cannot hold (anything but ASCII letters, digits and ``_``) ``_``; one that would not start with a letter
    gets ``s_`` in front."""
    name = re.sub(r"[^0-9A-Za-z_]", "_", signal.replace(".", "__"))
    return name if name[:1].isascii() and name[:1].isalpha() else f"s_{name}"


class FieldNumbers:
    """Signal -> protobuf field number, stable for a whole log (a signal keeps its number when the
    layout changes, so every layout's schema decodes every other layout's fields the same way)."""

    def __init__(self, known: Mapping[str, int] | None = None):
        self.numbers: dict[str, int] = dict(known or {})

    def number(self, signal: str) -> int:
        num = self.numbers.get(signal)
        if num is None:
            num = self.numbers[signal] = FIRST_SIGNAL_FIELD + len(self.numbers)
            if 19000 <= num <= 19999:  # reserved by protobuf
                num = self.numbers[signal] = 20000 + len(self.numbers)
        return num


@dataclass(frozen=True)
class Slot:
    name: str
    offset: int
    shape: tuple[int, ...]
    unit: str

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))


@dataclass(frozen=True)
class _Run:
    """Consecutive fields of equal header and data size: ``count`` records of ``head + data`` bytes.

    ``records`` views that part of a message row as records with a field ``h`` (the header bytes) and
    a field ``d`` (the values: one double, or ``data`` bytes), so a run is copied value by value, not
    byte by byte; ``values`` is how the matching bus bytes are viewed.
    """

    msg_start: int
    count: int
    head: int
    data: int
    bus_start: int  # in bytes

    @functools.cached_property
    def records(self) -> np.dtype:
        value = "<f8" if self.data == 8 else ("V", self.data)
        return np.dtype({"names": ["h", "d"], "formats": [("V", self.head), value], "offsets": [0, self.head],
                         "itemsize": self.head + self.data})

    @functools.cached_property
    def values(self) -> np.dtype:
        return np.dtype("<f8") if self.data == 8 else np.dtype(("V", self.data))

    def of(self, msgs: np.ndarray) -> np.ndarray:
        """The run's records in (n, length) message rows, as an (n, count) record array."""
        return msgs[:, self.msg_start:self.msg_start + self.count * (self.head + self.data)].view(self.records)

    def bus(self, rows_u8: np.ndarray) -> np.ndarray:
        """The run's values in (n, 8 * size) bus rows (as bytes), as an (n, count) array."""
        return rows_u8[:, self.bus_start:self.bus_start + self.count * self.data].view(self.values)


_MESSAGE_HEADER = np.dtype({"names": ["tick", "epoch", "time"], "formats": ["<u8", "<u8", "<f8"],
                            "offsets": [1, 10, 19], "itemsize": HEADER_BYTES})


def written_fields(slots: Sequence[Slot]) -> list[Slot]:
    """The signals written as fields: each bus value once, by its most specific name. A block is
    replaced by its named rows when they cover it exactly."""
    ordered = sorted((s for s in slots if s.size), key=lambda s: (s.offset, -s.size, s.name))
    out: list[Slot] = []
    i = 0
    while i < len(ordered):
        block = ordered[i]
        end = block.offset + block.size
        inner = []
        j = i + 1
        while j < len(ordered) and ordered[j].offset < end:
            inner.append(ordered[j])
            j += 1
        out.extend(inner if _tiles(block, inner) else [block])
        i = j
    return out


def _tiles(block: Slot, inner: list[Slot]) -> bool:
    at = block.offset
    for s in inner:
        if s.offset != at:
            return False
        at += s.size
    return bool(inner) and at == block.offset + block.size


class BusCodec:
    """The ``/bus`` messages of one layout: encode bus rows in batches, decode them back, bit-exact."""

    def __init__(self, slots: Sequence[Slot], numbers: FieldNumbers, size: int, key: int = 1, kind: str = "layout"):
        self.kind = kind  # "layout" (``/bus``) or "imagined" (an imagined branch's signals): names the schema
        self.slots = tuple(slots)
        self.by_name = {s.name: s for s in self.slots}
        self.size = size
        self.key = key
        self.fields = written_fields(self.slots)
        covered = sum(f.size for f in self.fields)
        if covered != size:
            raise ValueError(f"bus layout does not cover the bus: {covered} of {size} values")
        self.numbers = {f.name: numbers.number(f.name) for f in self.fields}
        template, runs = bytearray(HEADER_BYTES), []
        for f in self.fields:
            num = self.numbers[f.name]
            head = varint(num << 3 | 1) if f.shape == () else varint(num << 3 | 2) + varint(8 * f.size)
            last = runs[-1] if runs else None
            if last and last[2] == len(head) and last[3] == 8 * f.size and last[4] + last[1] * last[3] == 8 * f.offset:
                last[1] += 1
            else:
                runs.append([len(template), 1, len(head), 8 * f.size, 8 * f.offset])
            template += head + bytes(8 * f.size)
        for k, (_name, _num, tag) in enumerate(_HEADER_FIELDS):
            template[9 * k] = tag
        self.template = np.frombuffer(bytes(template), dtype=np.uint8)
        self.length = len(template)
        self.runs = tuple(_Run(*r) for r in runs)
        self._buf = np.empty((0, self.length), dtype=np.uint8)

    # -- encoding --------------------------------------------------------------------------------------
    def encode(self, rows: np.ndarray, ticks: np.ndarray, epochs: np.ndarray, dt_ns: int,
               out: np.ndarray | None = None) -> np.ndarray:
        """(n, size) float64 bus rows -> (n, length) uint8 messages, written into ``out`` (any (n, length)
        view whose rows are contiguous) or into a buffer of the codec's (valid until the next call)."""
        n = len(rows)
        if out is None:
            if len(self._buf) < n:
                self._buf = np.tile(self.template, (max(n, 64), 1))
            out = self._buf[:n]
        else:  # the template first, in one pass (row by row, in order), then the values: where ``out`` is
            # a chunk's fresh memory, writing each run's header bytes in a pass of their own (every cache line
            # of every message, once per run) cost the humanoid's 13 runs 2.2 us a tick, this 1.35
            out[...] = self.template
        ticks = np.asarray(ticks, dtype=np.int64)
        header = out[:, :HEADER_BYTES].view(_MESSAGE_HEADER)[:, 0]
        header["tick"], header["epoch"], header["time"] = ticks, epochs, ticks * dt_ns / 1e9
        src = np.ascontiguousarray(rows, dtype="<f8").view(np.uint8)
        for r in self.runs:
            r.of(out)["d"] = r.bus(src)
        return out

    def decode(self, msgs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n, length) uint8 messages -> (rows (n, size) float64, ticks, epochs)."""
        msgs = np.asarray(msgs, dtype=np.uint8).reshape(-1, self.length)
        rows = np.empty((len(msgs), self.size * 8), dtype=np.uint8)
        for r in self.runs:
            r.bus(rows)[...] = r.of(msgs)["d"]
        header = msgs[:, :HEADER_BYTES].view(_MESSAGE_HEADER)[:, 0]
        return rows.view("<f8"), header["tick"].astype(np.int64), header["epoch"].astype(np.int64)

    # -- description -----------------------------------------------------------------------------------
    @property
    def schema_name(self) -> str:
        return f"dynabrain.{self.kind}{self.key}.Bus"

    def descriptor(self) -> bytes:
        """The schema as a serialized protobuf FileDescriptorSet, built with protobuf's own descriptor
        classes and nothing that strict readers refuse: no ``SourceCodeInfo`` (Go's protodesc, and so the
        ``mcap`` CLI, rejects a location without a span: ``proto: invalid span: []``), so a field's unit
        is in the channel's metadata (``units``, `metadata`), not in a comment."""
        fd = descriptor_pb2.FileDescriptorProto(name=f"dynabrain/{self.kind}{self.key}.proto",
                                                package=f"dynabrain.{self.kind}{self.key}", syntax="proto3")
        msg = fd.message_type.add(name="Bus")
        fdp = descriptor_pb2.FieldDescriptorProto
        for name, num, _tag in _HEADER_FIELDS:
            kind = fdp.TYPE_DOUBLE if name == "time" else fdp.TYPE_FIXED64
            msg.field.add(name=name, number=num, type=kind, label=fdp.LABEL_OPTIONAL)
        used: set[str] = {"tick", "epoch", "time"}
        for f in self.fields:
            name = field_name(f.name)
            while name in used:
                name += "_"
            used.add(name)
            label = fdp.LABEL_OPTIONAL if f.shape == () else fdp.LABEL_REPEATED
            msg.field.add(name=name, number=self.numbers[f.name], type=fdp.TYPE_DOUBLE, label=label,
                          json_name=f.name)
        return descriptor_pb2.FileDescriptorSet(file=[fd]).SerializeToString()

    def units(self) -> dict[str, str]:
        """Signal -> unit of every field (``""``: none), for the channel's metadata: the schema holds no
        comments (see `descriptor`)."""
        return {f.name: f.unit for f in self.fields}

    def metadata(self) -> dict[str, str]:
        """Channel metadata from which `from_metadata` makes the same codec again."""
        return {"layout": json.dumps([[s.name, s.offset, list(s.shape), s.unit] for s in self.slots]),
                "bus_size": str(self.size), "fields": json.dumps(self.numbers), "layout_key": str(self.key),
                "units": json.dumps(self.units()),
                **({} if self.kind == "layout" else {"kind": self.kind})}

    @classmethod
    def from_metadata(cls, meta: Mapping[str, str]) -> BusCodec:
        slots = [Slot(n, int(o), tuple(int(x) for x in shape), u) for n, o, shape, u in json.loads(meta["layout"])]
        return cls(slots, FieldNumbers(json.loads(meta["fields"])), int(meta["bus_size"]),
                   int(meta.get("layout_key", "1")), meta.get("kind", "layout"))

    @classmethod
    def from_view(cls, slots: Mapping[str, tuple[int, tuple[int, ...], str]], size: int, numbers: FieldNumbers,
                  key: int) -> BusCodec:
        return cls([Slot(n, o, tuple(sh), u) for n, (o, sh, u) in slots.items()], numbers, size, key)

    def signature(self) -> tuple:
        return tuple((s.name, s.offset, s.shape, s.unit) for s in self.slots)


def padded_varints(values: np.ndarray, width: int = 5) -> np.ndarray:
    """(n,) non-negative integers -> (n, width) uint8 varints padded to ``width`` bytes."""
    values = np.asarray(values, dtype=np.uint64)
    shifts = np.arange(width, dtype=np.uint64) * np.uint64(7)
    out = ((values[:, None] >> shifts) & np.uint64(0x7F)).astype(np.uint8)
    out[:, :-1] |= 0x80
    return out


class PoseCodec:
    """``foxglove.FrameTransforms`` messages for a fixed list of bodies, encoded in batches.

    Transforms are written grouped by the length of the body's name (their order does not matter),
    so each group is an array of equal-sized records and every value is one strided copy per group.
    With few bodies, one indexed copy of every value byte costs less than the per-group copies.
    """

    FEW = 16

    def __init__(self, bodies: Sequence[str], parent: str = "world"):
        self.bodies = tuple(bodies)
        by_length: dict[int, list[int]] = {}
        for i, body in enumerate(self.bodies):
            by_length.setdefault(len(body.encode()), []).append(i)
        template = bytearray()
        self._groups: list[tuple[int, int, np.dtype, np.ndarray]] = []
        cols: list[np.ndarray] = [np.empty(0, np.intp)] * len(self.bodies)
        for members in by_length.values():
            start = len(template)
            for i in members:
                record, dtype = _transform_record(parent, self.bodies[i])
                at = len(template)
                cols[i] = np.concatenate([at + dtype.fields[f][1] + np.arange(8) for f in _VALUE_FIELDS]
                                         + [at + dtype.fields[f][1] + np.arange(5) for f in ("sec", "nsec")])
                template += record
            self._groups.append((start, len(members) * dtype.itemsize, dtype, np.array(members, dtype=np.intp)))
        self._cols = np.concatenate(cols) if cols else np.empty(0, np.intp)
        self.template = np.frombuffer(bytes(template), dtype=np.uint8)
        self.length = len(template)
        self._buf = np.empty((0, self.length), dtype=np.uint8)

    def encode(self, pos: np.ndarray, quat_wxyz: np.ndarray, t_ns: np.ndarray, out: np.ndarray | None = None
               ) -> np.ndarray:
        """pos (n, bodies, 3), quat (n, bodies, 4) w-x-y-z, times (n,) ns -> (n, length) uint8, written
        into ``out`` or into a buffer of the codec's (valid until the next call)."""
        n = len(t_ns)
        if out is None:
            if len(self._buf) < n:
                self._buf = np.tile(self.template, (max(n, 64), 1))
            out = self._buf[:n]
        else:
            out[:] = self.template
        t_ns = np.asarray(t_ns, dtype=np.int64)
        seconds = padded_varints(t_ns // 1_000_000_000)[:, None, :]
        nanos = padded_varints(t_ns % 1_000_000_000)[:, None, :]
        nb = len(self.bodies)
        if nb <= self.FEW:
            values = np.empty((n, nb, 66), dtype=np.uint8)
            doubles = values[:, :, :56].view("<f8")
            doubles[:, :, :3], doubles[:, :, 3:6], doubles[:, :, 6] = pos, quat_wxyz[..., 1:], quat_wxyz[..., 0]
            values[:, :, 56:61], values[:, :, 61:] = seconds, nanos
            out[:, self._cols] = values.reshape(n, -1)
            return out
        values = (pos[..., 0], pos[..., 1], pos[..., 2], quat_wxyz[..., 1], quat_wxyz[..., 2], quat_wxyz[..., 3],
                  quat_wxyz[..., 0])
        for start, size, dtype, members in self._groups:
            recs = out[:, start:start + size].view(dtype)
            recs["sec"] = seconds
            recs["nsec"] = nanos
            for k, value in enumerate(values):
                recs[_VALUE_FIELDS[k]] = value[:, members]
        return out


_VALUE_FIELDS = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")


def _transform_record(parent: str, body: str) -> tuple[bytes, np.dtype]:
    """One FrameTransform (field 1 of FrameTransforms) with zero values, and the record type locating
    its timestamp varints and its seven doubles (translation x y z, rotation x y z w)."""
    tf = bytearray(b"\x0a\x0c\x08")  # timestamp (12 bytes): seconds, then nanos, 5-byte varints
    stamp_at = len(tf)
    tf += bytes(5) + b"\x10" + bytes(5)
    tf += b"\x12" + varint(len(parent.encode())) + parent.encode()
    tf += b"\x1a" + varint(len(body.encode())) + body.encode()
    cols = []
    for sub, tags in ((b"\x22\x1b", (0x09, 0x11, 0x19)), (b"\x2a\x24", (0x09, 0x11, 0x19, 0x21))):
        tf += sub  # Vector3 translation, then Quaternion rotation: a tag byte and 8 bytes per value
        for tag in tags:
            cols.append(len(tf) + 1)
            tf += bytes([tag]) + bytes(8)
    head = b"\x0a" + varint(len(tf))
    base = len(head)
    dtype = np.dtype({"names": ["sec", "nsec", *_VALUE_FIELDS],
                      "formats": [("u1", (5,)), ("u1", (5,))] + ["<f8"] * 7,
                      "offsets": [base + stamp_at, base + stamp_at + 6] + [base + c for c in cols],
                      "itemsize": len(head) + len(tf)})
    return head + tf, dtype


def pose_columns(core_name: str, bodies: Sequence[str], codec: BusCodec) -> tuple[np.ndarray, list[str]]:
    """Per body, the 7 columns (x y z qw qx qy qz) of its pose in a bus row, extended by the poses of
    the bodies whose ``<core>.<body>.pos`` / ``.quat`` are not on the bus (those are asked from the core)."""
    cols, missing = [], []
    for body in bodies:
        pos, quat = codec.by_name.get(f"{core_name}.{body}.pos"), codec.by_name.get(f"{core_name}.{body}.quat")
        if pos is not None and quat is not None and pos.shape == (3,) and quat.shape == (4,):
            cols.append([pos.offset + k for k in range(3)] + [quat.offset + k for k in range(4)])
        else:
            at = codec.size + 7 * len(missing)
            cols.append(list(range(at, at + 7)))
            missing.append(body)
    return np.array(cols, dtype=np.intp).reshape(-1, 7), missing


def foxglove_descriptor(message_class: type) -> bytes:
    """A serialized FileDescriptorSet holding a protobuf message class and everything it uses."""
    files: dict[str, descriptor_pb2.FileDescriptorProto] = {}

    def add(fd) -> None:
        if fd.name in files:
            return
        for dep in fd.dependencies:
            add(dep)
        proto = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(proto)
        files[fd.name] = proto

    add(message_class.DESCRIPTOR.file)
    return descriptor_pb2.FileDescriptorSet(file=list(files.values())).SerializeToString()


def event_bytes(event: dict) -> bytes:
    return json.dumps(event, default=_plain, separators=(",", ":")).encode()


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (set, frozenset, tuple)):
        return list(value)
    return repr(value)
