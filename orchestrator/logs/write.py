"""A lean MCAP writer (https://mcap.dev/spec): chunked, zstd-compressed, indexed, crash-tolerant.

Why not the ``mcap`` package's writer: it costs about 3.4 us a message in Python, a third of a
two-cube tick by itself. Here a batch of equal-sized messages (one per tick of a channel) becomes
message records with a few numpy operations, written straight into a reusable chunk buffer (fresh
memory for every chunk would cost a page fault per 4 KiB). Files are read back by the ``mcap``
package in the tests, as an independent check.

Finished chunks are compressed (``compression``: zstd, the default, at ``level`` -1, its first fast level;
lz4; or none) and written by a thread of the writer's own, so compression overlaps the simulation on a
second core. On the humanoid's log (about 9.4 KB a tick before compression, mostly float64 bus values)
zstd costs the most of the writer's CPU time: per tick and 4 MB chunk, level 1 14.5 us for a 2.58
ratio, -1 12.3 us for 2.54, -2 11.1 us for 2.41, -3 10.3 us for 2.24, -5 9.5 us for 1.91; lz4 11.3 us
for 1.97; a crc32 of the chunk 1.3 us, so a zstd chunk carries zstd's own checksum of its content
instead (0.3 us; the chunk's MCAP CRC is 0, which the spec reads as none; decompressing checks it), and
lz4 and uncompressed chunks a CRC (measured on this 2-core machine, ``bench/logging_cost.py``
prints the writer's whole time). A chunk goes to the file with one ``os.writev`` of its header, its
compressed data and its message indexes (no copy of the compressed data).
A caller can hand that thread whole jobs (`call`: encode a batch and add it, for instance): every
writer call made inside a job runs there, in order, and its chunks are compressed there too.

Order. Messages go into the file in log-time order, within and across chunks, as the MCAP spec
recommends and strict readers (``mcap doctor --strict-message-order``) require: `add_group` takes the
batches of several channels (a run's bus, poses, scenes and events over the same ticks), merges them
by log time (stable: at equal times, in the order the parts are given) and writes them in that order,
finishing chunks between two messages. Each part is encoded where it lands when its messages are
equally spaced there (a strided view into the chunk: the usual case), else into scratch memory and
copied run by run. A message whose log time is below one already written is still written (a caller
that rolls time back, such as a world's rollback); `out_of_order` counts them, so that the caller can
put the file in order afterwards (`logs.recover.rewrite`).

Crash safety. Bytes go to the file with ``os.write`` (no user-space buffer), one chunk at a time, so a
process killed with SIGKILL leaves every chunk that was written. A chunk is finished when it holds
``chunk_bytes`` of records, when its messages would span ``chunk_ns`` of log time (1 s by default: in a
dynabrain log, whose log time runs with the simulated time, a run faster than real time is chunked
finely too) or when its
first record is ``flush_s`` seconds old (checked whenever a record is added), so a kill loses the
chunk being filled and the finished ones still waiting for the thread (at most ``QUEUE_DEPTH`` jobs;
in practice they are written within milliseconds).

Damage. Every chunk declares the schemas and channels of its own messages (a channel's records go into
each chunk before its first message there, and into the summary), so any chunk decodes on its own: a
damaged chunk loses its own messages only, and a reader that resynchronises on the next valid chunk
(`logs.scan` in lenient mode, ``dynabrain log recover``) keeps everything after it. The MCAP spec allows
these repeated records (identical each time); ``mcap doctor`` notes them as duplicates, a warning.
"""

from __future__ import annotations

import os
import queue
import struct
import threading
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import numpy as np
import zstandard

from ..kernel.errors import DynabrainError

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_STATISTICS, OP_METADATA = 0x07, 0x08, 0x0B, 0x0C
OP_METADATA_INDEX, OP_SUMMARY_OFFSET, OP_DATA_END = 0x0D, 0x0E, 0x0F
QUEUE_DEPTH = 2
"""Jobs (finished chunks, `McapWriter.call` jobs) waiting for the writing thread; a producer faster than
the thread waits beyond this."""
CHUNK_NS = 1_000_000_000
"""Log time one chunk spans at most by default (ns): one second of simulated time."""
COMPRESSIONS = ("zstd", "lz4", "none")
"""A chunk's compression: zstd (at ``level``), lz4 (its frame format, the fastest level) or none."""
IOV_MAX = os.sysconf("SC_IOV_MAX") if hasattr(os, "sysconf") and "SC_IOV_MAX" in os.sysconf_names else 16
"""Buffers one ``os.writev`` takes at most (more take more calls)."""
MESSAGE_HEADER = struct.Struct("<BQHIQQ")
"""opcode, record length, channel id, sequence, log time, publish time (then the data)."""


def pack_str(text: str) -> bytes:
    raw = text.encode()
    return struct.pack("<I", len(raw)) + raw


def pack_map(values: Mapping[str, str]) -> bytes:
    body = b"".join(pack_str(k) + pack_str(v) for k, v in values.items())
    return struct.pack("<I", len(body)) + body


def record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


def _batch_dtype(length: int) -> np.dtype:
    """Message records with ``length`` bytes of data, packed, as one numpy record type."""
    return np.dtype({"names": ["op", "len", "ch", "seq", "log", "pub"],
                     "formats": ["u1", "<u8", "<u2", "<u4", "<u8", "<u8"],
                     "offsets": [0, 1, 9, 11, 15, 23], "itemsize": 31 + length})


class Part(NamedTuple):
    """Messages of one channel for `McapWriter.add_group`, all of ``length`` bytes, in log-time order:
    ``fill(out, part)`` writes the messages ``part`` (a slice of this part's messages) into ``out``, an
    (k, length) uint8 array whose rows are contiguous. ``publish_times`` default to the log times."""

    channel_id: int
    log_times: np.ndarray
    sequences: np.ndarray
    length: int
    fill: Callable[[np.ndarray, slice], None]
    publish_times: np.ndarray | None = None


class _Chunk:
    """A chunk being filled: a reusable byte buffer, its message index and time range."""

    def __init__(self, capacity: int):
        self.buf = np.empty(capacity, dtype=np.uint8)
        self.reset()

    def reset(self) -> None:
        self.pos = 0
        self.declared: set[int] = set()  # channels whose records (and schema's) this chunk holds
        self.schemas: set[int] = set()
        self.index: dict[int, list[np.ndarray]] = {}
        self.t_min: int | None = None
        self.t_max = 0
        self.born: float | None = None
        self.messages = 0

    def put(self, data: bytes) -> None:
        self.buf[self.pos:self.pos + len(data)] = np.frombuffer(data, dtype=np.uint8)
        self.pos += len(data)

    def room(self) -> int:
        return len(self.buf) - self.pos

    def timed(self, channel_id: int, times: np.ndarray, offsets: np.ndarray) -> None:
        self.index.setdefault(channel_id, []).append(np.stack([times, offsets], axis=1))
        lo, hi = int(times.min()), int(times.max())
        self.t_min = lo if self.t_min is None else min(self.t_min, lo)
        self.t_max = max(self.t_max, hi)
        self.messages += len(times)
        if self.born is None:
            self.born = time.monotonic()


class McapWriter:
    """Writes one MCAP file. One thread adds records (the world's stepping thread), directly or in jobs
    handed to the writer's own thread (`call`); the writer's thread compresses and writes chunks."""

    def __init__(self, path: str | os.PathLike[str], *, chunk_bytes: int = 1 << 20, flush_s: float = 0.25,
                 chunk_ns: int | None = CHUNK_NS, level: int = -1, compression: str = "zstd", profile: str = "",
                 library: str = "dynabrain"):
        self.path = os.fspath(path)
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as exc:
            raise DynabrainError(f"cannot write the log {self.path}: {exc.strerror}") from None
        if chunk_ns is not None and (isinstance(chunk_ns, bool) or not isinstance(chunk_ns, int) or chunk_ns < 1):
            raise DynabrainError(f"McapWriter: chunk_ns must be a positive integer or None, got {chunk_ns!r}")
        self.chunk_bytes, self.flush_s, self.chunk_ns = chunk_bytes, flush_s, chunk_ns
        if compression not in COMPRESSIONS:
            raise DynabrainError(f"McapWriter: compression must be one of {', '.join(map(repr, COMPRESSIONS))}, "
                                 f"got {compression!r}")
        self.compression = "" if compression == "none" else compression
        self._compress = _compressor(self.compression, level)
        self._pos = 0
        self._schemas: dict[int, bytes] = {}
        self._channels: dict[int, bytes] = {}
        self._schema_of: dict[int, int] = {}  # channel id -> its schema id
        self._counts: dict[int, int] = {}
        self._chunk_indexes: list[bytes] = []
        self._metadata_indexes: list[bytes] = []
        self._dtypes: dict[int, np.dtype] = {}
        self.messages = self.chunks = 0
        self.out_of_order = 0
        """Messages written with a log time below one written before them (see the module docstring)."""
        self._last_time = 0
        self.thread_cpu_s = 0.0
        """CPU time the writing thread has spent (compressing and writing)."""
        self.compress_cpu_s = 0.0
        """Of which compressing chunks."""
        self._t_min: int | None = None
        self._t_max = 0
        self._spare: queue.LifoQueue[_Chunk] = queue.LifoQueue()  # the buffer freed last is reused first: warm
        self._made = 1
        self._chunk = _Chunk(2 * chunk_bytes)
        self._error: BaseException | None = None
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue(maxsize=QUEUE_DEPTH)
        self._write(MAGIC + record(OP_HEADER, pack_str(profile) + pack_str(library)))
        self._thread = threading.Thread(target=self._work, name=f"dynabrain-mcap-{os.path.basename(self.path)}",
                                        daemon=True)
        self._thread.start()

    def warm_up(self) -> None:
        """Make every chunk buffer now and touch its memory, and let the compressor allocate its
        tables: a fresh process then pays for none of it while a run is being written."""
        while self._made < QUEUE_DEPTH + 2:
            self._made += 1
            self._spare.put(_Chunk(2 * self.chunk_bytes))
        for chunk in [self._chunk, *self._spare.queue]:
            chunk.buf[chunk.pos:].fill(0)  # (records already in the chunk stay)
        self._compress(bytes(self.chunk_bytes))

    def call(self, job: Callable[[], None]) -> None:
        """Run ``job`` on the writing thread after everything handed to it before. Writer calls made
        inside it run there too (a chunk it finishes is compressed there). A job that raises stops the
        writer: the error comes back as a `DynabrainError` from the next call, `call` or `finish`."""
        self._submit(job)

    # -- registration ---------------------------------------------------------------------------------
    def add_schema(self, name: str, encoding: str, data: bytes, schema_id: int | None = None) -> int:
        sid = schema_id if schema_id is not None else len(self._schemas) + 1
        rec = record(OP_SCHEMA, struct.pack("<H", sid) + pack_str(name) + pack_str(encoding)
                     + struct.pack("<I", len(data)) + data)
        self._schemas[sid] = rec  # into each chunk that uses it (`_declare`) and into the summary
        return sid

    def add_channel(self, topic: str, encoding: str, schema_id: int, metadata: Mapping[str, str] | None = None,
                    channel_id: int | None = None) -> int:
        cid = channel_id if channel_id is not None else len(self._channels) + 1
        rec = record(OP_CHANNEL, struct.pack("<HH", cid, schema_id) + pack_str(topic) + pack_str(encoding)
                     + pack_map(metadata or {}))
        self._channels[cid] = rec  # into each chunk that uses it (`_declare`) and into the summary
        self._schema_of[cid] = schema_id
        self._counts.setdefault(cid, 0)
        return cid

    def add_metadata(self, name: str, values: Mapping[str, str]) -> None:
        """A metadata record, written to the file at once (outside chunks)."""
        rec = record(OP_METADATA, pack_str(name) + pack_map(values))

        def job() -> None:
            self._metadata_indexes.append(record(OP_METADATA_INDEX, struct.pack("<QQ", self._pos, len(rec))
                                                 + pack_str(name)))
            self._write(rec)

        self._submit(job)

    # -- messages -------------------------------------------------------------------------------------
    def add_message(self, channel_id: int, log_time: int, data: bytes, sequence: int = 0,
                    publish_time: int | None = None) -> None:
        self._within_span(log_time)
        self._ordered(log_time, 1)
        offset = self._declare([channel_id], 31 + len(data))
        pub = log_time if publish_time is None else publish_time
        self._chunk.put(MESSAGE_HEADER.pack(OP_MESSAGE, 22 + len(data), channel_id, sequence, log_time, pub) + data)
        self._indexed(channel_id, np.array([log_time], dtype=np.uint64), np.array([offset], dtype=np.uint64))

    def add_messages(self, channel_id: int, log_times: np.ndarray, sequences: np.ndarray, data: np.ndarray,
                     publish_times: np.ndarray | None = None) -> None:
        """A batch of messages of one channel, all of the same size: ``data`` is (n, length) uint8."""
        def copy(out: np.ndarray, part: slice) -> None:
            out[:] = data[part]

        self.add_encoded(channel_id, log_times, sequences, data.shape[1], copy, publish_times)

    def add_encoded(self, channel_id: int, log_times: np.ndarray, sequences: np.ndarray, length: int,
                    fill: Callable[[np.ndarray, slice], None], publish_times: np.ndarray | None = None) -> None:
        """A batch of ``len(log_times)`` messages of ``length`` bytes, encoded in place: ``fill(out, part)``
        writes the messages ``part`` of the batch into ``out``, a (k, length) view into the chunk."""
        self.add_group([Part(channel_id, log_times, sequences, length, fill, publish_times)])

    def add_group(self, parts: Sequence[Part]) -> None:
        """Batches of several channels (`Part`, each in log-time order), merged by log time (at equal
        times, in the order of ``parts``) and written in that order, chunks finished between messages."""
        parts = [p for p in parts if len(p.log_times)]
        if not parts:
            return
        merged = _Merge(parts)
        done, n = 0, merged.n
        self._ordered(int(merged.times[0]), int(np.searchsorted(merged.times, self._last_time, "left")))
        channels = list(dict.fromkeys(p.channel_id for p in parts))
        while done < n:
            self._within_span(int(merged.times[done]))
            start = self._declare(channels, int(merged.sizes[done]))
            chunk = self._chunk
            cap = max(min(chunk.room(), self.chunk_bytes - start), int(merged.sizes[done]))
            k = max(1, int(np.searchsorted(merged.ends, merged.ends[done] - merged.sizes[done] + cap, "right")) - done)
            if self.chunk_ns is not None and k > 1:  # the chunk spans less than chunk_ns of log time
                t_min = chunk.t_min if chunk.messages else int(merged.times[done])
                k = max(1, min(k, int(np.searchsorted(merged.times[done:done + k], t_min + self.chunk_ns, "left"))))
            self._place(merged, done, done + k, start)
            done += k
            if chunk.pos >= self.chunk_bytes or time.monotonic() - chunk.born >= self.flush_s:
                self.flush()

    def _ordered(self, log_time: int, behind: int) -> None:
        """Count the messages of a batch starting at ``log_time`` that go below the latest log time."""
        if log_time < self._last_time:
            self.out_of_order += max(behind, 1)

    def _declare(self, channels: list[int], first: int) -> int:
        """Put the records of ``channels`` into the chunk (those it lacks), with room after them for a
        message of ``first`` bytes (a fresh or larger chunk when needed); where the messages start."""
        decl = self._declarations(channels)
        if self._chunk.room() < len(decl) + first:
            self.flush()
            decl = self._declarations(channels)
            if self._chunk.room() < len(decl) + first:  # a record larger than a chunk buffer: a larger buffer
                old = self._chunk
                self._chunk = _Chunk(old.pos + len(decl) + first + self.chunk_bytes)
                self._chunk.put(old.buf[:old.pos].tobytes())
                self._chunk.declared, self._chunk.schemas = old.declared, old.schemas
                self._made += 1
        chunk = self._chunk
        if decl:
            chunk.put(decl)
            for cid in channels:
                chunk.declared.add(cid)
                chunk.schemas.add(self._schema_of.get(cid, 0))
        return chunk.pos

    def _declarations(self, channels: list[int]) -> bytes:
        chunk, out, schemas = self._chunk, [], set(self._chunk.schemas)
        for cid in channels:
            if cid in chunk.declared:
                continue
            channel = self._channels.get(cid)
            if channel is None:
                raise DynabrainError(f"writing the log {self.path}: a message on channel {cid}, which was never "
                                     "added")
            sid = self._schema_of[cid]
            if sid not in schemas:
                out.append(self._schemas.get(sid, b""))
                schemas.add(sid)
            out.append(channel)
        return b"".join(out)

    def _place(self, merged: _Merge, lo: int, hi: int, start: int) -> None:
        """Write the merged messages ``[lo, hi)`` from ``start`` in the chunk (they fit), part by part."""
        chunk = self._chunk
        buf = chunk.buf
        base = merged.ends[lo] - merged.sizes[lo]
        for p, (a, b) in merged.ranges(lo, hi):
            part = merged.parts[p]
            size = 31 + part.length
            dest = (merged.ends[merged.positions[p][a:b]] - size - base + start).astype(np.int64)
            dtype = self._dtypes.get(part.length)
            if dtype is None:
                dtype = self._dtypes[part.length] = _batch_dtype(part.length)
            times = np.asarray(part.log_times[a:b], dtype=np.uint64)
            pubs = times if part.publish_times is None else part.publish_times[a:b]
            m = b - a
            step = int(dest[1] - dest[0]) if m > 1 else size
            in_place = m == 1 or bool(np.all(np.diff(dest) == step))
            if in_place:  # equally spaced (the usual case): encoded where they land, through a strided view
                recs = np.ndarray((m,), dtype, buffer=buf, offset=int(dest[0]), strides=(step,))
                out = np.ndarray((m, part.length), np.uint8, buffer=buf, offset=int(dest[0]) + 31, strides=(step, 1))
            else:
                scratch = np.empty((m, size), dtype=np.uint8)
                recs, out = scratch.view(dtype)[:, 0], scratch[:, 31:]
            recs["op"], recs["len"], recs["ch"] = OP_MESSAGE, 22 + part.length, part.channel_id
            recs["seq"], recs["log"], recs["pub"] = part.sequences[a:b], times, pubs
            part.fill(out, slice(a, b))
            if not in_place:
                _scatter(buf, scratch, dest)
            chunk.timed(part.channel_id, times, dest.astype(np.uint64))
            self._counts[part.channel_id] = self._counts.get(part.channel_id, 0) + m
            self.messages += m
        chunk.pos = start + int(merged.ends[hi - 1] - base)
        self._last_time = max(self._last_time, int(merged.times[hi - 1]))

    def _indexed(self, channel_id: int, times: np.ndarray, offsets: np.ndarray) -> None:
        self._chunk.timed(channel_id, times, offsets)
        self._counts[channel_id] = self._counts.get(channel_id, 0) + len(times)
        self.messages += len(times)
        self._last_time = max(self._last_time, int(times.max()))
        chunk = self._chunk
        if chunk.pos >= self.chunk_bytes or time.monotonic() - chunk.born >= self.flush_s:
            self.flush()

    def _within_span(self, log_time: int) -> None:
        """Finish the chunk when a message at ``log_time`` would make it span ``chunk_ns`` or more."""
        chunk = self._chunk
        if self.chunk_ns is not None and chunk.messages and (max(chunk.t_max, log_time)
                                                             - min(chunk.t_min, log_time) >= self.chunk_ns):
            self.flush()

    # -- chunks ---------------------------------------------------------------------------------------
    def flush(self) -> None:
        """Finish the chunk being filled (if it holds a message); the writing thread compresses and
        writes it. Records of a chunk without messages (schemas, channels) wait for the next one."""
        chunk = self._chunk
        if chunk.messages == 0:
            return
        self._submit(lambda: self._write_chunk(chunk))
        self._chunk = self._next_buffer()
        self._chunk.reset()

    def _next_buffer(self) -> _Chunk:
        try:
            return self._spare.get_nowait()
        except queue.Empty:
            if self._made < QUEUE_DEPTH + 2:
                self._made += 1
                return _Chunk(2 * self.chunk_bytes)
        while True:  # every buffer is waiting to be written: wait for one
            try:
                return self._spare.get(timeout=0.1)
            except queue.Empty:
                self._check()

    def _write_chunk(self, chunk: _Chunk) -> None:
        size, t_min, t_max, index = chunk.pos, chunk.t_min or 0, chunk.t_max, chunk.index
        try:
            raw = memoryview(chunk.buf)[:size]
            t0 = time.thread_time()
            packed = self._compress(raw)
            self.compress_cpu_s += time.thread_time() - t0
            # a zstd frame carries a checksum of its content (xxh64: 0.3 us a humanoid tick where a crc32
            # of the chunk costs 1.3), which decompressing checks: the chunk's CRC is then 0 ("none" in MCAP)
            crc = 0 if self.compression == "zstd" else zlib.crc32(raw)
            del raw
        finally:
            self._spare.put(chunk)  # the buffer is free again (also when this failed)
        kind = pack_str(self.compression)
        body = struct.pack("<QQQI", t_min, t_max, size, crc) + kind + struct.pack("<Q", len(packed))
        head = struct.pack("<BQ", OP_CHUNK, len(body) + len(packed)) + body
        chunk_len = len(head) + len(packed)
        start, at = self._pos, self._pos + chunk_len
        indexes, offsets = [], {}
        for cid, parts in index.items():
            entries = np.concatenate(parts)
            entries = entries[np.argsort(entries[:, 0], kind="stable")]
            rec = record(OP_MESSAGE_INDEX, struct.pack("<HI", cid, entries.nbytes) + entries.astype("<u8").tobytes())
            offsets[cid] = at
            at += len(rec)
            indexes.append(rec)
        self._write(head, packed, *indexes)  # one system call, no copy of the compressed data
        body = struct.pack("<QQQQ", t_min, t_max, start, chunk_len)
        body += struct.pack("<I", 10 * len(offsets)) + b"".join(struct.pack("<HQ", c, o) for c, o in offsets.items())
        body += struct.pack("<Q", at - start - chunk_len) + kind + struct.pack("<QQ", len(packed), size)
        self._chunk_indexes.append(record(OP_CHUNK_INDEX, body))
        self.chunks += 1
        self._t_min = t_min if self._t_min is None else min(self._t_min, t_min)
        self._t_max = max(self._t_max, t_max)

    def _write(self, *data: bytes) -> None:
        """Write ``data`` (byte strings, in order) to the file, with as few system calls as it takes."""
        views = [memoryview(d) for d in data if len(d)]
        self._pos += sum(len(v) for v in views)
        while views:
            try:
                done = os.writev(self._fd, views[:IOV_MAX])
            except OSError as exc:
                raise DynabrainError(f"writing the log {self.path} failed: {exc.strerror}") from None
            while views and done >= len(views[0]):
                done -= len(views.pop(0))
            if views:
                views[0] = views[0][done:]

    # -- the writing thread ---------------------------------------------------------------------------
    def _submit(self, job: Callable[[], None]) -> None:
        if threading.get_ident() == self._thread.ident:  # inside a job: now, in order
            job()
            return
        self._check()
        self._jobs.put(job)

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            t0 = time.thread_time()
            try:
                if job is None:
                    return
                if self._error is None:
                    job()
            except BaseException as exc:
                self._error = exc
            finally:
                self.thread_cpu_s += time.thread_time() - t0
                self._jobs.task_done()

    def check(self) -> None:
        """Raise the error that stopped the writing thread, if one did (as a `DynabrainError`)."""
        self._check()

    def _check(self) -> None:
        exc = self._error
        if isinstance(exc, DynabrainError):
            raise exc
        if exc is not None:
            raise DynabrainError(f"writing the log {self.path} failed: {type(exc).__name__}: {exc}") from exc

    # -- the end --------------------------------------------------------------------------------------
    def finish(self) -> None:
        """Write the last chunk, the summary (schemas, channels, statistics, indexes) and the footer."""
        self._jobs.join()  # jobs handed over with `call` may still add messages
        self._check()
        self.flush()
        self._jobs.join()
        self._check()
        # 0: no data-section CRC (chunks have theirs: a CRC or zstd's checksum)
        self._write(record(OP_DATA_END, struct.pack("<I", 0)))
        start = self._pos
        groups = [(OP_SCHEMA, list(self._schemas.values())), (OP_CHANNEL, list(self._channels.values())),
                  (OP_STATISTICS, [self._statistics()]), (OP_CHUNK_INDEX, self._chunk_indexes),
                  (OP_METADATA_INDEX, self._metadata_indexes)]
        summary = bytearray()
        offsets = bytearray()
        for opcode, recs in groups:
            if recs:
                offsets += record(OP_SUMMARY_OFFSET, struct.pack("<BQQ", opcode, start + len(summary),
                                                                  sum(map(len, recs))))
                summary += b"".join(recs)
        offset_start = start + len(summary)
        summary += offsets
        head = struct.pack("<BQQQ", OP_FOOTER, 20, start, offset_start)
        crc = zlib.crc32(head, zlib.crc32(summary))
        self._write(bytes(summary) + head + struct.pack("<I", crc) + MAGIC)
        self.close()

    def _statistics(self) -> bytes:
        counts = b"".join(struct.pack("<HQ", c, n) for c, n in sorted(self._counts.items()))
        return record(OP_STATISTICS, struct.pack("<QHIIIIQQ", self.messages, len(self._schemas), len(self._channels),
                                                 0, len(self._metadata_indexes), self.chunks, self._t_min or 0,
                                                 self._t_max) + struct.pack("<I", len(counts)) + counts)

    def close(self) -> None:
        """Stop the writing thread and close the file as it is (`finish` writes the summary first)."""
        if self._fd < 0:
            return
        self._jobs.put(None)
        self._thread.join()
        os.close(self._fd)
        self._fd = -1

    @property
    def bytes_written(self) -> int:
        return self._pos


def _compressor(compression: str, level: int) -> Callable[[memoryview | bytes], bytes]:
    if compression == "zstd":
        return zstandard.ZstdCompressor(level=level, write_checksum=True).compress  # (see `_write_chunk`)
    if compression == "lz4":
        import lz4.frame

        def lz4_frame(data: memoryview | bytes) -> bytes:  # the chunk's CRC covers the data: no checksum of lz4's
            return lz4.frame.compress(data, compression_level=0, content_checksum=False, store_size=True)

        return lz4_frame
    return bytes


class _Merge:
    """Parts merged by log time (stable): per merged message its time, size and end offset (sizes
    summed), and per part where its messages went."""

    def __init__(self, parts: Sequence[Part]):
        self.parts = parts
        counts = [len(p.log_times) for p in parts]
        times = np.concatenate([np.asarray(p.log_times, dtype=np.uint64) for p in parts])
        sizes = np.concatenate([np.full(c, 31 + p.length, dtype=np.int64) for c, p in zip(counts, parts, strict=True)])
        order = np.argsort(times, kind="stable") if len(parts) > 1 else np.arange(len(times))
        self.n = len(times)
        self.times, self.sizes = times[order], sizes[order]
        self.ends = np.cumsum(self.sizes)
        where = np.empty(self.n, dtype=np.int64)
        where[order] = np.arange(self.n)
        bounds = np.concatenate([[0], np.cumsum(counts)])
        self.positions = [where[bounds[i]:bounds[i + 1]] for i in range(len(parts))]
        """Per part, the merged position of each of its messages (increasing: a part keeps its order)."""

    def ranges(self, lo: int, hi: int) -> list[tuple[int, tuple[int, int]]]:
        """Per part with messages among the merged ``[lo, hi)``: (part, its messages' range)."""
        out = []
        for p, pos in enumerate(self.positions):
            a, b = int(np.searchsorted(pos, lo)), int(np.searchsorted(pos, hi))
            if b > a:
                out.append((p, (a, b)))
        return out


def _scatter(buf: np.ndarray, records: np.ndarray, dest: np.ndarray) -> None:
    """Copy (m, size) records to the offsets ``dest`` of ``buf``, one strided copy per run of equally
    spaced offsets."""
    m, size = records.shape
    gaps = np.diff(dest)
    at = 0
    while at < m:
        end = at + 1
        if end < m:
            step = gaps[at]
            change = np.flatnonzero(gaps[at:] != step)
            end = at + 1 + (int(change[0]) if len(change) else m - 1 - at)
        step = int(gaps[at]) if end - at > 1 else size
        view = np.ndarray((end - at, size), np.uint8, buffer=buf, offset=int(dest[at]), strides=(step, 1))
        view[...] = records[at:end]
        at = end
