"""The sinks the logger uses (`logs.logger`): `ProcessSink` runs a `logs.sink.LogSink` in a child process
(the default), `ThreadSink` on the writer's thread of this process. See `logs.sink` for what a sink does
and why the child process.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import time
from collections import deque
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError
from ..kernel.workers import spawn_worker
from . import sink
from .messages import (
    Abort,
    Call,
    Done,
    Failed,
    Finish,
    Finished,
    Open,
    Ready,
    Release,
    Rows,
    RowsPart,
    Shared,
    Span,
)
from .shared_rows import SharedRows, remove_stale_rows
from .sink import FINISH_TIMEOUT_S, NOTHING_WRITTEN, START_TIMEOUT_S, LogSink, reply_reason


# -- the sinks the logger uses ----------------------------------------------------------------------------
class ThreadSink:
    """The sink on the writer's thread of this process."""

    def __init__(self, path: str, writer_args: Mapping[str, Any], dt_ns: int, decimate: int,
                 bodies: Sequence[str] | None, descriptors: Mapping[str, bytes], ros2: bool = False):
        self._sink = LogSink(path, writer_args, dt_ns, decimate, bodies, descriptors, ros2)
        self._writer = self._sink.writer
        self._stats: dict[str, float] = {}

    @staticmethod
    def new_rows(shape: tuple[int, ...]) -> tuple[np.ndarray, None]:
        """An array for rows (the writer's thread reads it as it is)."""
        return np.empty(shape), None

    def call(self, call: Call) -> None:
        sink = self._sink
        self._writer.call(lambda: sink.apply(call))

    def rows(self, parts: list[Span | Release]) -> None:
        """Write the spans, in order; a `Release` hands its block back to its pool once everything
        before it is written."""
        sink = self._sink

        def job() -> None:
            for part in parts:
                block = part.block
                if type(part) is Release:
                    block.pool.append(block)
                    continue
                lo, hi = part.lo, part.hi
                sink.rows(block.codec.key, block.rows[lo:hi], None if block.extra is None else block.extra[lo:hi],
                          block.first + lo, block.epoch, part.discarded,
                          [(r - lo, s) for r, s in block.scenes if lo <= r < hi])

        self._writer.call(job)

    def release(self, block: Any) -> None:
        self._writer.call(lambda: block.pool.append(block))

    def poll(self) -> None:
        """Nothing to collect: blocks go back to their pools on the writer's thread."""

    def wait(self) -> None:
        """Give the writer's thread time to hand a block back."""
        self._writer.check()
        time.sleep(0.0005)

    def finish(self) -> dict[str, float]:
        self._stats = self._sink.finish()
        return self._stats

    def abort(self) -> None:
        self._writer.close()

    @property
    def stats(self) -> dict[str, float]:
        w = self._writer
        return self._stats or {"messages": w.messages, "chunks": w.chunks, "bytes": w.bytes_written,
                               "writer_cpu_s": w.thread_cpu_s, "encode_cpu_s": self._sink.encode_cpu_s,
                               "compress_cpu_s": w.compress_cpu_s, "out_of_order": w.out_of_order}


class ProcessSink:
    """The sink in a child process (see the module docstring)."""

    def __init__(self, path: str, writer_args: Mapping[str, Any], dt_ns: int, decimate: int,
                 bodies: Sequence[str] | None, descriptors: Mapping[str, bytes], ros2: bool = False):
        try:  # refuse a path that cannot be written here and now, not at the child's first write
            os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644))
        except OSError as exc:
            raise DynabrainError(f"cannot write the log {path}: {exc.strerror}") from None
        self.path = path
        remove_stale_rows()
        try:
            self._proc, self._conn = spawn_worker(sink.__name__)  # (its `__main__` serves)
        except OSError as exc:
            raise DynabrainError(f"cannot start the log writer process for {path}: {exc}") from None
        self._seq = 0
        self._releases: deque[tuple[int, list[Any]]] = deque()
        self._shared: list[SharedRows] = []
        self._error: str | None = None
        self._stats: dict[str, float] = {}
        try:
            self._send(Open(path, dict(writer_args), dt_ns, decimate, None if bodies is None else list(bodies),
                            dict(descriptors), ros2))
            reply = self._wait(START_TIMEOUT_S, "start")  # ready, or why not
            if type(reply) is not Ready:
                raise DynabrainError(reply_reason(reply))
        except BaseException:
            self._end()
            raise

    def new_rows(self, shape: tuple[int, ...]) -> tuple[np.ndarray, SharedRows]:
        """An array for rows in shared memory, and its handle (the child maps it by its path)."""
        rows = SharedRows(shape)
        self._shared.append(rows)
        return rows.array, rows

    def call(self, call: Call) -> None:
        self._send(call)

    def rows(self, parts: list[Span | Release]) -> None:
        batch, freed = [], []
        for part in parts:
            block = part.block
            if type(part) is Release:
                freed.append(block)
                continue
            lo, hi = part.lo, part.hi
            extra = None if block.extra is None else Shared(block.shared_extra.path, block.extra.shape)
            batch.append(RowsPart(block.codec.key, Shared(block.shared_rows.path, block.rows.shape), extra, lo, hi,
                                  block.first, block.epoch, part.discarded,
                                  [(r - lo, s) for r, s in block.scenes if lo <= r < hi]))
        if batch:
            self._send(Rows(batch))
        if freed:
            self._releases.append((self._seq, freed))
        self.poll()

    def release(self, block: Any) -> None:
        self._releases.append((self._seq, [block]))
        self.poll()

    def poll(self) -> None:
        """Take the child's acknowledgements: blocks whose rows it has encoded go back to their pools."""
        conn = self._conn
        try:
            while conn.poll():
                self._take(conn.recv())
        except (EOFError, OSError):
            self._error = self._error or f"the log writer process for {self.path} ended ({self._exit()})"
        self._check()

    def wait(self) -> None:
        """Wait for the child's next acknowledgement (a block is free again)."""
        if not self._conn.poll(FINISH_TIMEOUT_S):
            raise DynabrainError(f"the log writer process for {self.path} wrote nothing for {FINISH_TIMEOUT_S:g} s "
                                 f"({self._exit()})")
        self.poll()

    def finish(self) -> dict[str, float]:
        try:
            self._send(Finish())
            reply = self._wait(FINISH_TIMEOUT_S, "finish")
            if type(reply) is not Finished:
                raise DynabrainError(reply_reason(reply))
            self._stats = reply.stats
        finally:
            self._end(wait=False)  # the file is complete: no need to wait for the process to exit
        return self._stats

    def abort(self) -> None:
        with contextlib.suppress(Exception):
            self._send(Abort())
        self._end()

    @property
    def stats(self) -> dict[str, float]:
        return self._stats or NOTHING_WRITTEN

    # -- plumbing ---------------------------------------------------------------------------------------
    def _send(self, message: Open | Call | Rows | Finish | Abort) -> None:
        self._check()
        try:
            self._conn.send(message)
        except (OSError, ValueError) as exc:
            raise DynabrainError(f"the log writer process for {self.path} is gone ({self._exit()}): {exc}") from None
        if type(message) is Rows:
            self._seq += 1

    def _take(self, message: Done | Failed | Any) -> None:
        if type(message) is Done:
            while self._releases and self._releases[0][0] <= message.batches:
                for block in self._releases.popleft()[1]:
                    block.pool.append(block)
        else:
            self._error = reply_reason(message)

    def _wait(self, timeout: float, what: str) -> Ready | Finished | Failed | Any:
        """The child's next answer that is not an acknowledgement."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            try:
                ready = self._conn.poll(max(left, 0.0))
            except (OSError, EOFError):
                ready = True
            if not ready:
                raise DynabrainError(f"the log writer process for {self.path} did not {what} within {timeout:g} s")
            try:
                message = self._conn.recv()
            except (OSError, EOFError):
                return Failed(f"the log writer process for {self.path} ended ({self._exit()})")
            if type(message) is Done:
                self._take(message)
                continue
            return message

    def _check(self) -> None:
        if self._error is not None:
            raise DynabrainError(self._error)

    def _exit(self) -> str:
        try:
            code = self._proc.wait(1.0)
        except subprocess.TimeoutExpired:
            return "still running"
        return f"killed by signal {-code}" if code < 0 else f"exit code {code}"

    def _end(self, wait: bool = True) -> None:
        """Close the pipe (the child ends when it sees that), and free the shared rows. ``wait``: until
        the child has exited (killing it after a few seconds); else `subprocess` reaps it later."""
        with contextlib.suppress(Exception):
            self._conn.close()
        if wait:
            try:
                self._proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        for rows in self._shared:
            rows.release()
        self._shared.clear()
