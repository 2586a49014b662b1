"""Rewriting a log: recover what a killed run left, and compact a log after long rollbacks.

`rewrite` copies a file record by record into a new, complete one (summary, indexes, footer). In a
dynabrain log it also moves every message that is not part of the run (see `logs.read.final_mask`) to
its ``/discarded/...`` topic, so ``/bus``, ``/tf`` and ``/scene`` hold exactly what finally happened
(``/imagined/...`` topics are left as they are: what a brain imagined is no discarded future).
With ``lenient=True`` (``dynabrain log recover``) a damaged record is skipped instead of failing: the
scan resynchronises on the next valid chunk (`logs.scan`), so every intact chunk is kept, before and
after the damage, and a file cut short keeps everything up to its last complete chunk. A message whose
channel was declared only in lost bytes cannot be decoded and is dropped (counted). Times and
sequence numbers are kept as they were; so is the messages' order when their log times never decrease
in it, else they are written in log-time order (stable: at equal times, in the order they were in),
which needs every message of the file in memory at once (a log whose world rolled back).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from .read import LogIndex, family, read_index, run_family
from .scan import Channel, Damage, Message, Schema, scan
from .schema import DISCARDED, TOPIC_BUS
from .write import McapWriter


@dataclass(frozen=True)
class RewriteReport:
    complete: bool
    """The source was whole: its footer read and nothing damaged (nothing was lost)."""
    chunks: int
    """Chunks of the source read whole."""
    messages: int
    lost_bytes: int
    """Bytes of the source skipped: damaged regions and an unfinished end."""
    problem: str
    """What was wrong with the source (the first damage, and how many more), or empty."""
    ticks: tuple[int, int] | None
    """First and last tick of the run kept, for a dynabrain log."""
    moved: int
    """Messages moved to /discarded/... topics."""
    damaged: tuple[Damage, ...] = ()
    """The regions of the source that were skipped, in file order."""
    dropped: int = 0
    """Messages dropped because their channel was declared only in lost bytes."""
    run_ticks: int = 0
    """Ticks of the run kept (bus messages that are the run), for a dynabrain log."""


def rewrite(src: str | os.PathLike[str], dst: str | os.PathLike[str], *, lenient: bool = False) -> RewriteReport:
    """Write ``dst`` from ``src`` (see the module docstring). ``dst`` is written whole or not at all."""
    src, dst = os.fspath(src), os.fspath(dst)
    index = read_index(src, lenient=lenient)
    finals = {fam: index.final(fam) for fam in index.keys} if index.info is not None else None
    header = index.header
    part = dst + ".part"
    writer = McapWriter(part, profile=header.profile if header else "", library=header.library if header else "")
    try:
        for name, values in index.metadata.items():
            writer.add_metadata(name, values)
        moved, dropped = _copy_records(src, index, writer, finals, lenient)
        writer.finish()
    except BaseException:
        writer.close()
        if os.path.exists(part):
            os.remove(part)
        raise
    os.replace(part, dst)
    report = index.report
    run = _run_ticks(index, finals)
    return RewriteReport(report.complete and not report.damaged, report.chunks, writer.messages, report.lost_bytes,
                         report.problem, (min(run), max(run)) if run else None, moved, tuple(report.damaged),
                         dropped, len(run))


def _copy_records(src: str, index: LogIndex, writer: McapWriter, finals: dict[str, set[int]] | None,
                  lenient: bool) -> tuple[int, int]:
    """Copy every record; returns (messages moved to /discarded/..., messages dropped)."""
    channels: dict[int, Channel] = {}
    schemas: set[int] = set()
    moved_ids: dict[int, int] = {}
    next_id = max(index.channels, default=0) + 1
    moved = dropped = pos = 0
    held: list[tuple[int, int, int, Message]] | None = None if index.ordered else []
    for rec in scan(src, lenient=lenient):
        if isinstance(rec, Schema) and rec.id not in schemas:
            schemas.add(rec.id)
            writer.add_schema(rec.name, rec.encoding, rec.data, schema_id=rec.id)
        elif isinstance(rec, Channel) and rec.id not in channels:
            channels[rec.id] = rec
            writer.add_channel(rec.topic, rec.encoding, rec.schema_id, rec.metadata, channel_id=rec.id)
        elif isinstance(rec, Message):
            pos += 1
            cid = rec.channel_id
            ch = channels.get(cid)
            if ch is None:  # its channel was declared in lost bytes: nothing can read it
                dropped += 1
                continue
            if finals is not None and run_family(ch.topic) in finals:
                fam = family(ch.topic)
                target = fam if pos in finals[run_family(fam)] else DISCARDED + fam
                if target != ch.topic:
                    moved += 1
                    if cid not in moved_ids:
                        moved_ids[cid] = writer.add_channel(target, ch.encoding, ch.schema_id, ch.metadata,
                                                            channel_id=next_id)
                        next_id += 1
                    cid = moved_ids[cid]
            if held is None:
                writer.add_message(cid, rec.log_time, rec.data, rec.sequence, rec.publish_time)
            else:
                held.append((rec.log_time, pos, cid, rec))
    for log_time, _pos, cid, msg in sorted(held or (), key=lambda h: (h[0], h[1])):
        writer.add_message(cid, log_time, msg.data, msg.sequence, msg.publish_time)
    return moved, dropped


def _run_ticks(index: LogIndex, finals: dict[str, set[int]] | None) -> list[int]:
    if finals is None or TOPIC_BUS not in finals:
        return []
    return [t for _e, t, p in index.keys[TOPIC_BUS] if p in finals[TOPIC_BUS]]


def recover(src: str | os.PathLike[str], dst: str | os.PathLike[str] | None = None) -> tuple[str, RewriteReport]:
    """Write a valid log from what ``src`` holds (every complete chunk); returns (path, report)."""
    src = os.fspath(src)
    if dst is None:
        stem = src[:-5] if src.endswith(".mcap") else src
        dst = stem + ".recovered.mcap"
    return os.fspath(dst), rewrite(src, dst, lenient=True)
