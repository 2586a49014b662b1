"""Reading MCAP files record by record, in file order, from any writer.

`scan` yields the records of a file (the records inside chunks, decompressed, in place of the chunk)
and tells, at the end, whether the file was complete. A file that stops in the middle of a record (a
run that was killed, a copy cut short) raises `TruncatedLogError` in strict mode; in lenient mode (what
`dynabrain log recover` uses) the scan stops before the first incomplete or damaged record and reports
where. Bad input gets one clear error naming the file.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import BinaryIO

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


@dataclass(frozen=True)
class Metadata:
    name: str
    values: dict[str, str]


@dataclass(frozen=True)
class Header:
    profile: str
    library: str


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
    """Why the scan stopped early (lenient mode), empty when it did not."""
    unknown: dict[int, int] = field(default_factory=dict)
    """Records of opcodes this reader does not know (a newer MCAP version), by opcode."""


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
            if len(head) < 9:
                _stop(path, report, pos, lenient, "the file ends before its footer" if not head else
                      "the file ends inside a record header")
                return
            opcode, length = struct.unpack("<BQ", head)
            if length > MAX_RECORD or pos + 9 + length > report.size:
                _stop(path, report, pos, lenient, f"a record at byte {pos} runs past the end of the file")
                return
            body = fh.read(length)
            try:
                records = list(_decode(opcode, body, report))
            except (struct.error, UnicodeDecodeError, zstandard.ZstdError, ValueError) as exc:
                _stop(path, report, pos, lenient, f"the record at byte {pos} is damaged ({exc})")
                return
            pos += 9 + length
            report.good_bytes = pos
            yield from records
            if opcode == OP_FOOTER:
                report.complete = fh.read(8) == MAGIC
                if not report.complete:
                    _stop(path, report, pos, lenient, "the footer is not followed by the MCAP magic bytes")
                return


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


def _stop(path: str, report: ScanReport, pos: int, lenient: bool, why: str) -> None:
    report.problem = why
    if not lenient:
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

        data = lz4.frame.decompress(data)
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
    cid, seq, log_time, _pub = struct.unpack_from("<HIQQ", buf, start)
    return Message(cid, seq, log_time, buf[start + 22:end])


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
