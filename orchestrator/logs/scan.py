"""Reading MCAP files record by record, in file order, from any writer.

`scan` yields the records of a file (the records inside chunks, decompressed, in place of the chunk)
and tells, at the end, whether the file was complete. A file that stops in the middle of a record (a
run that was killed, a copy cut short) or holds a damaged one raises `TruncatedLogError` in strict
mode. In lenient mode (what `dynabrain log recover` uses) a damaged record is skipped: the scan
resynchronises on the next valid chunk (a chunk record whose fields agree with each other and whose
data decompresses to its size and CRC, or, for zstd, with its frame's checksum: `logs.write`), as the
official MCAP tools skip an invalid chunk, and goes on;
a file cut short ends the scan. There, a record of an unknown opcode, or a message outside chunks in a
chunked file, counts as damage too (reading out of step lands on such bytes). Every region skipped is
reported (`ScanReport.damaged`). Since each chunk declares its own channels (`logs.write`), damage
loses the messages of the damaged chunk only.
Bad input gets one clear error naming the file.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import BinaryIO

import numpy as np
import zstandard

from ..kernel.errors import DynabrainError
from .write import (
    MAGIC,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE,
    OP_METADATA,
    OP_SCHEMA,
)

MAX_RECORD = 1 << 32
RESYNC_WINDOW = 4 << 20
"""Bytes read at a time while looking for the next valid chunk after a damaged record."""
_COMPRESSIONS = ("", "zstd", "lz4")


class LogError(DynabrainError):
    """A log file that cannot be read: missing, not MCAP, damaged."""


class TruncatedLogError(LogError):
    """A log that ends in the middle of a record (a killed run): `dynabrain log recover` mends it."""


@dataclass(frozen=True)
class Schema:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class Channel:
    id: int
    schema_id: int
    topic: str
    encoding: str
    metadata: dict[str, str]


@dataclass(frozen=True)
class Message:
    channel_id: int
    sequence: int
    log_time: int
    data: bytes
    publish_time: int = 0


@dataclass(frozen=True)
class Metadata:
    name: str
    values: dict[str, str]


@dataclass(frozen=True)
class Header:
    profile: str
    library: str


@dataclass(frozen=True)
class Damage:
    """Bytes ``[start, end)`` of a file that a lenient scan skipped, and why."""

    start: int
    end: int
    why: str


@dataclass
class ScanReport:
    """How a scan ended."""

    complete: bool = False
    """The file ends with a footer and the magic bytes."""
    chunks: int = 0
    """Chunks read whole."""
    good_bytes: int = 0
    """Bytes up to the end of the last record read whole."""
    size: int = 0
    problem: str = ""
    """What was wrong (lenient mode): the first damage, and how many more; empty when nothing was."""
    damaged: list[Damage] = field(default_factory=list)
    """Regions skipped (lenient mode), in file order; a file cut short ends with one that reaches its end."""
    unknown: dict[int, int] = field(default_factory=dict)
    """Records of opcodes this reader does not know (a newer MCAP version), by opcode."""

    @property
    def lost_bytes(self) -> int:
        """Bytes skipped as damaged or cut short."""
        return sum(d.end - d.start for d in self.damaged)

    def skip(self, start: int, end: int, why: str) -> None:
        self.damaged.append(Damage(start, end, why))
        first = self.damaged[0].why
        self.problem = first if len(self.damaged) == 1 else f"{first} (and {len(self.damaged) - 1} more damaged " \
                                                              "regions, skipped)"


def scan(path: str | os.PathLike[str], report: ScanReport | None = None, *, lenient: bool = False
         ) -> Iterator[Header | Schema | Channel | Message | Metadata]:
    """The records of an MCAP file in file order (chunks opened). See the module docstring."""
    path = os.fspath(path)
    report = report if report is not None else ScanReport()
    fh = open_log_file(path)
    with fh:
        report.size = os.fstat(fh.fileno()).st_size
        pos = len(MAGIC)
        report.good_bytes = pos
        while True:
            head = fh.read(9)
            why = ""
            if len(head) < 9:
                why = "the file ends before its footer" if not head else "the file ends inside a record header"
            else:
                opcode, length = struct.unpack("<BQ", head)
                if length > MAX_RECORD or pos + 9 + length > report.size:
                    why = f"a record at byte {pos} runs past the end of the file"
                elif lenient and (opcode > OP_DATA_END or (opcode == OP_MESSAGE and report.chunks)):
                    why = f"the record at byte {pos} is damaged (opcode {opcode:#04x} is not expected there)"
                else:
                    body = fh.read(length)
                    try:
                        records = list(_decode(opcode, body, report))
                    except (struct.error, UnicodeDecodeError, zstandard.ZstdError, ValueError) as exc:
                        why = f"the record at byte {pos} is damaged ({exc})"
            if why:
                _stop(path, report, lenient, why)
                found = _resync(fh, pos + 1, report.size)
                report.skip(pos, report.size if found is None else found, why)
                if found is None:
                    return
                pos = found
                fh.seek(pos)
                continue
            pos += 9 + length
            report.good_bytes = pos
            yield from records
            if opcode == OP_FOOTER:
                report.complete = fh.read(8) == MAGIC
                if not report.complete:
                    why = "the footer is not followed by the MCAP magic bytes"
                    _stop(path, report, lenient, why)
                    report.skip(pos, report.size, why)
                return


def _resync(fh: BinaryIO, start: int, size: int) -> int | None:
    """The offset of the next valid chunk record at or after ``start`` (see the module docstring), or None."""
    at = start
    while at < size:
        fh.seek(at)
        window = fh.read(RESYNC_WINDOW + 64)
        if not window:
            return None
        for i in np.flatnonzero(np.frombuffer(window, dtype=np.uint8)[:RESYNC_WINDOW] == OP_CHUNK).tolist():
            if _chunk_at(fh, window, i, at + i, size):
                return at + i
        at += RESYNC_WINDOW
    return None


def _chunk_at(fh: BinaryIO, window: bytes, i: int, offset: int, size: int) -> bool:
    """Whether a whole, valid chunk record starts at ``offset`` (``window[i]``)."""
    if i + 41 > len(window):
        return False
    (length,) = struct.unpack_from("<Q", window, i + 1)
    (clen,) = struct.unpack_from("<I", window, i + 37)  # the compression's name: "", "zstd" or "lz4"
    if clen > 4 or length < 40 + clen or offset + 9 + length > size:
        return False
    fh.seek(offset + 9)
    body = fh.read(length)
    try:
        compression, at = _str(body, 28)
        (data,) = struct.unpack_from("<Q", body, at)
        if compression not in _COMPRESSIONS or at + 8 + data != length:
            return False
        for _ in _chunk(body):
            pass
    except (struct.error, UnicodeDecodeError, zstandard.ZstdError, ValueError):
        return False
    return True


def open_log_file(path: str) -> BinaryIO:
    """Open ``path`` and check the MCAP magic bytes; clear errors for a missing or foreign file."""
    try:
        fh = open(path, "rb")  # noqa: SIM115 (the caller closes it)
    except FileNotFoundError:
        raise LogError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise LogError(f"{path} is a folder, not a log file") from None
    except OSError as exc:
        raise LogError(f"cannot read {path}: {exc.strerror}") from None
    magic = fh.read(len(MAGIC))
    if magic != MAGIC:
        fh.close()
        what = "it is empty" if not magic else "it does not start with the MCAP magic bytes"
        raise LogError(f"{path} is not an MCAP file ({what})")
    return fh


def _stop(path: str, report: ScanReport, lenient: bool, why: str) -> None:
    """Strict mode: raise, saying why. (Lenient mode goes on: the caller skips the damage.)"""
    if not lenient:
        report.problem = why
        raise TruncatedLogError(f"{path} is truncated or damaged: {why} (read {report.good_bytes} of {report.size} "
                                f"bytes; a run that is still recording, or was killed, leaves its log so); "
                                f"`dynabrain log recover {path}` writes a valid file with every complete chunk")


def _decode(opcode: int, body: bytes, report: ScanReport):
    if opcode == OP_MESSAGE:
        yield _message(body, 0, len(body))
    elif opcode == OP_CHUNK:
        yield from _chunk(body)
        report.chunks += 1
    elif opcode == OP_SCHEMA:
        yield _schema(body)
    elif opcode == OP_CHANNEL:
        yield _channel(body)
    elif opcode == OP_METADATA:
        name, at = _str(body, 0)
        values, _ = _map(body, at)
        yield Metadata(name, values)
    elif opcode == OP_HEADER:
        profile, at = _str(body, 0)
        library, _ = _str(body, at)
        yield Header(profile, library)
    elif opcode > OP_DATA_END:
        report.unknown[opcode] = report.unknown.get(opcode, 0) + 1


def _chunk(body: bytes):
    _t0, _t1, size, crc = struct.unpack_from("<QQQI", body, 0)
    compression, at = _str(body, 28)
    (length,) = struct.unpack_from("<Q", body, at)
    data = body[at + 8:at + 8 + length]
    if len(data) != length:
        raise ValueError("chunk data is shorter than its length")
    if compression == "zstd":
        data = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    elif compression == "lz4":
        import lz4.frame

        try:
            data = lz4.frame.decompress(data)
        except RuntimeError as exc:  # lz4's error for a damaged frame
            raise ValueError(f"the chunk's lz4 data does not decompress: {exc}") from None
    elif compression:
        raise ValueError(f"unknown compression {compression!r}")
    if len(data) != size or (crc and zlib.crc32(data) != crc):
        raise ValueError("chunk size or CRC does not match its data")
    at, end = 0, len(data)
    while at < end:
        opcode, length = struct.unpack_from("<BQ", data, at)
        start = at + 9
        at = start + length
        if at > end:
            raise ValueError("a record runs past the end of its chunk")
        if opcode == OP_MESSAGE:
            yield _message(data, start, at)
        elif opcode == OP_SCHEMA:
            yield _schema(data[start:at])
        elif opcode == OP_CHANNEL:
            yield _channel(data[start:at])


def _message(buf: bytes, start: int, end: int) -> Message:
    cid, seq, log_time, pub = struct.unpack_from("<HIQQ", buf, start)
    return Message(cid, seq, log_time, buf[start + 22:end], pub)


def _schema(body: bytes) -> Schema:
    (sid,) = struct.unpack_from("<H", body, 0)
    name, at = _str(body, 2)
    encoding, at = _str(body, at)
    (length,) = struct.unpack_from("<I", body, at)
    return Schema(sid, name, encoding, bytes(body[at + 4:at + 4 + length]))


def _channel(body: bytes) -> Channel:
    cid, sid = struct.unpack_from("<HH", body, 0)
    topic, at = _str(body, 4)
    encoding, at = _str(body, at)
    metadata, _ = _map(body, at)
    return Channel(cid, sid, topic, encoding, metadata)


def _str(buf: bytes, at: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, at)
    end = at + 4 + n
    if end > len(buf):
        raise ValueError("a string runs past the end of its record")
    return bytes(buf[at + 4:end]).decode(), end


def _map(buf: bytes, at: int) -> tuple[dict[str, str], int]:
    (n,) = struct.unpack_from("<I", buf, at)
    at += 4
    end = at + n
    out: dict[str, str] = {}
    while at < end:
        key, at = _str(buf, at)
        out[key], at = _str(buf, at)
    return out, end
