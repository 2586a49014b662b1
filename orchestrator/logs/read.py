"""Reading a log: its index (metadata, channels, events, which messages are the run) and its bus rows.

`read_index` scans a file once and keeps everything but the message data: per channel the count and
time range, the events of a dynabrain log (in the order they were produced: by ``seq``), and each
message's (epoch, tick) for `final_mask`, the rule that tells the run from what rollbacks discarded
(see `logs.logger`). A message's tick is its publish time (simulated time) over the step; its log time
is the wall-clock start plus that (`logs.schema`). Files from other tools are read too (channels,
counts, times); they just have no dynabrain metadata.
"""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .meta import RunInfo
from .scan import Channel, Header, LogError, Message, Metadata, ScanReport, Schema, scan
from .schema import DISCARDED, FORMAT, IMAGINED, METADATA_NAME, TOPIC_BUS, TOPIC_EVENTS, BusCodec, bus_family


def family(topic: str) -> str:
    """``/discarded/bus`` -> ``/bus``: the topic a discarded message would have had."""
    return topic[len(DISCARDED):] if topic.startswith(DISCARDED + "/") else topic


def run_family(topic: str) -> str:
    """The topics whose messages share ticks: ``/discarded/bus/layout2`` -> ``/bus``, ``/discarded/tf``
    -> ``/tf``."""
    return bus_family(family(topic))


@dataclass
class LogIndex:
    path: str
    report: ScanReport
    header: Header | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)
    times: dict[int, tuple[int, int]] = field(default_factory=dict)
    events: list[dict] = field(default_factory=list)
    keys: dict[str, list[tuple[int, int, int]]] = field(default_factory=dict)
    """Per topic family (`run_family`): (epoch, tick, file position) of each message (``/imagined/...``
    topics have none: they are not the run, and rollbacks do not apply to them)."""
    ordered: bool = True
    """The messages' log times never decrease in file order (what strict MCAP readers require)."""

    @property
    def info(self) -> RunInfo | None:
        """The run's metadata, when this is a dynabrain log."""
        meta = self.metadata.get(METADATA_NAME)
        if meta is None or meta.get("format") != FORMAT:
            return None
        try:
            return RunInfo.parse(meta)
        except (KeyError, ValueError) as exc:
            raise LogError(f"{self.path}: the dynabrain metadata is damaged ({exc})") from None

    @property
    def rollbacks(self) -> dict[int, int]:
        """Epoch ended -> the tick the rollback went back to."""
        out = {}
        for ev in self.events:
            if ev.get("kind") == "rollback":
                try:
                    out[int(ev["detail"]["epoch"]) - 1] = int(ev["detail"]["to_tick"])
                except (KeyError, TypeError, ValueError):
                    raise LogError(f"{self.path}: rollback event {ev.get('seq')} is damaged: {ev}") from None
        return out

    def final(self, topic_family: str) -> set[int]:
        """File positions of the messages of ``topic_family`` that make up the run."""
        keys = self.keys.get(topic_family, [])
        mask = final_mask([(e, t) for e, t, _ in keys], self.rollbacks)
        return {pos for (_e, _t, pos), keep in zip(keys, mask, strict=True) if keep}

    def bus_codec(self, channel_id: int) -> BusCodec:
        ch = self.channels[channel_id]
        try:
            return BusCodec.from_metadata(ch.metadata)
        except (KeyError, ValueError, TypeError) as exc:
            raise LogError(f"{self.path}: channel {ch.topic} (id {channel_id}) has no usable bus layout ({exc})"
                           ) from None

    def is_bus(self, channel_id: int) -> bool:
        ch = self.channels.get(channel_id)
        return ch is not None and run_family(ch.topic) == TOPIC_BUS and "layout" in ch.metadata

    @property
    def time_range(self) -> tuple[int, int] | None:
        if not self.times:
            return None
        return min(t[0] for t in self.times.values()), max(t[1] for t in self.times.values())


def read_index(path: str | os.PathLike[str], *, lenient: bool = False) -> LogIndex:
    """Scan ``path`` once (see the module docstring). Strict by default: a truncated file raises. Only
    a regular file is read (a FIFO would hang the reader, a device never end)."""
    if os.path.exists(path) and not os.path.isfile(path):
        raise LogError(f"{os.fspath(path)} is not a regular file (a FIFO, a device or a folder): not a log")
    index = LogIndex(os.fspath(path), ScanReport())
    dt_ns, pos, dynabrain, latest = 1, 0, False, 0
    for rec in scan(path, index.report, lenient=lenient):
        if isinstance(rec, Message):
            pos += 1
            _count(index, rec)
            if rec.log_time < latest:
                index.ordered = False
            latest = max(latest, rec.log_time)
            ch = index.channels.get(rec.channel_id)
            if ch is None:
                continue
            if ch.topic == TOPIC_EVENTS and dynabrain:
                index.events.append(_event(rec, ch, index))
            elif not ch.topic.startswith(IMAGINED + "/"):  # what a brain imagined is no part of the run
                index.keys.setdefault(run_family(ch.topic), []).append((rec.sequence, rec.publish_time // dt_ns,
                                                                         pos))
        elif isinstance(rec, Channel):
            index.channels[rec.id] = rec
        elif isinstance(rec, Schema):
            index.schemas[rec.id] = rec
        elif isinstance(rec, Metadata):
            index.metadata[rec.name] = rec.values
            if rec.name == METADATA_NAME and rec.values.get("format") == FORMAT:
                dynabrain = True
                dt_ns = int(rec.values["dt_ns"]) if rec.values.get("dt_ns", "").isdigit() else 1
        elif isinstance(rec, Header):
            index.header = rec
    index.events.sort(key=lambda e: e.get("seq", 0) if isinstance(e.get("seq"), int) else 0)
    return index


def _count(index: LogIndex, msg: Message) -> None:
    cid = msg.channel_id
    index.counts[cid] = index.counts.get(cid, 0) + 1
    lo, hi = index.times.get(cid, (msg.log_time, msg.log_time))
    index.times[cid] = (min(lo, msg.log_time), max(hi, msg.log_time))


def _event(msg: Message, ch: Channel, index: LogIndex) -> dict:
    """An event: a ``foxglove.Log`` whose message is the event's JSON, or (logs written before) the JSON."""
    path, text = index.path, msg.data
    schema = index.schemas.get(ch.schema_id)
    if ch.encoding == "protobuf" and schema is not None and schema.name == "foxglove.Log":
        from foxglove_schemas_protobuf.Log_pb2 import Log
        from google.protobuf.message import DecodeError

        try:
            text = Log.FromString(msg.data).message
        except DecodeError as exc:
            raise LogError(f"{path}: an event at log time {msg.log_time} ns is not a foxglove.Log ({exc})") from None
    try:
        event = json.loads(text)
    except ValueError as exc:
        raise LogError(f"{path}: an event at log time {msg.log_time} ns is not valid JSON ({exc})") from None
    if not isinstance(event, dict) or "kind" not in event:
        raise LogError(f"{path}: an event at log time {msg.log_time} ns has no kind")
    return event


def final_mask(keys: list[tuple[int, int]], rollbacks: dict[int, int]) -> np.ndarray:
    """Which of the messages (epoch, tick) of one topic make up the run.

    In the order the messages were produced (by epoch, then tick), each message replaces any kept
    message of the same or a later tick, and the rollback that ends epoch e drops the kept messages of
    ticks after the tick it went back to.
    """
    order = sorted(range(len(keys)), key=lambda i: (keys[i][0], keys[i][1], i))
    stack: list[tuple[int, int]] = []
    epoch = 0

    def roll_until(target: int) -> int:
        e = epoch
        while e < target:
            back = rollbacks.get(e)
            if back is not None:
                while stack and stack[-1][0] > back:
                    stack.pop()
            e += 1
        return e

    for i in order:
        e, tick = keys[i]
        epoch = roll_until(e)
        while stack and stack[-1][0] >= tick:
            stack.pop()
        stack.append((tick, i))
    roll_until(max(rollbacks, default=-1) + 1)
    mask = np.zeros(len(keys), dtype=bool)
    mask[[i for _t, i in stack]] = True
    return mask


class BusRow(NamedTuple):
    """One bus message, decoded."""

    codec: BusCodec
    epoch: int
    tick: int
    row: np.ndarray
    pos: int
    """Position of the message in the file (1 for the first message)."""
    topic: str


def iter_bus(path: str | os.PathLike[str], index: LogIndex, *, lenient: bool = False, produced: bool = False
             ) -> Iterator[BusRow]:
    """Every bus message (of the run and discarded ones), decoded, in file order; ``produced``: in the
    order the world produced them (by epoch, then tick: a log with rollbacks holds them in log-time
    order, where a rollback's ticks sit beside the ticks it discarded; those are sorted in memory)."""
    keys = index.keys.get(TOPIC_BUS, [])
    if produced and any((a[0], a[1]) > (b[0], b[1]) for a, b in itertools.pairwise(keys)):
        yield from sorted(_iter_bus(path, index, lenient), key=lambda r: (r.epoch, r.tick, r.pos))
    else:
        yield from _iter_bus(path, index, lenient)


def _iter_bus(path: str | os.PathLike[str], index: LogIndex, lenient: bool) -> Iterator[BusRow]:
    codecs: dict[int, BusCodec] = {}
    pos = 0
    for rec in scan(path, lenient=lenient):
        if not isinstance(rec, Message):
            continue
        pos += 1
        if not index.is_bus(rec.channel_id):
            continue
        codec = codecs.get(rec.channel_id)
        if codec is None:
            codec = codecs[rec.channel_id] = index.bus_codec(rec.channel_id)
        if len(rec.data) != codec.length:
            raise LogError(f"{index.path}: a bus message at log time {rec.log_time} ns has {len(rec.data)} bytes, "
                           f"its layout {codec.length}")
        rows, ticks, epochs = codec.decode(np.frombuffer(rec.data, dtype=np.uint8))
        yield BusRow(codec, int(epochs[0]), int(ticks[0]), rows[0], pos, index.channels[rec.channel_id].topic)
