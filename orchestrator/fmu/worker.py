"""The child process of an isolated FMU (``isolate: true``): runs one `Session` for its parent.

    python -m dynabrain.orchestrator.fmu.worker FD TRACE_FILE

Requests come over the connection on file descriptor FD as tuples ``(op, *args)``; each gets
``("ok", value)`` or ``("error", class name, FMI call, message, lost, port)``; ``lost``: the instance cannot
be used any more (a fatal error, or a failure it cannot restore a state from before; see `session`);
``port``: the output a `NonFiniteOutputError` names.
Before each FMI call the worker writes the call's name into TRACE_FILE (shared memory), so when the
FMU kills the process the parent can say which call did it; a step goes through the C step helper
(`fastpath`), which writes the number of its call there instead (a store, not a Python call).
States cross as serialized bytes: they outlive this process.

Steps take a shorter way (`attach`): the parent writes the step's time and inputs into a shared
memory file (`IO_HEADER` int64 words, then the inputs, the outputs and the state's bytes) and sends
the one-byte message `STEP`; the worker steps, writes the outputs there, serializes the state straight
into it, and answers `DONE` (or a pickled error, as for any request). Nothing is pickled on the way,
and one message crosses each way: about 60 us less per step than a pickled request and reply. The
worker's side of a passthrough step costs 9-17 us here at a load of 4.5 on 2 cores (23-25 us with the
step's calls made from Python and the state copied twice; 3.5 us on an idle machine); the rest is the
round trip between the processes (`bench/fmu_chain.py`).
"""

from __future__ import annotations

import ctypes
import mmap
import os
import pickle
import signal
import sys
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError, ModuleError
from .info import FmuInfo
from .session import Session
from .states import FMUState, SerializedFMUState

TRACE_SIZE = 64
TRACE_FILE_BYTES = TRACE_SIZE + 8
"""The trace file: the call's name (Python's calls), then an int32 the C step helper writes: the number
of its call under way (`fastpath.CALLS`), 0 between steps."""
IO_HEADER = 4
"""int64 words at the start of the step's shared memory: t_ns, dt_ns, the state's length (-1: too long
for the file, the parent asks `last_state`; -2: no state kept), and the state's capacity in bytes."""
STEP, DONE = b"S", b"D"


class Worker:
    def __init__(self, trace: mmap.mmap):
        self.trace = trace
        self.session: Session | None = None
        self.keep: FMUState | None = None  # the current state (its slot stays taken while it is current)
        self.io: mmap.mmap | None = None
        self.last: bytes | None = None  # the last step's serialized state, when it did not fit the file

    def mark(self, call: str) -> None:
        self.trace[:TRACE_SIZE] = call.encode()[:TRACE_SIZE].ljust(TRACE_SIZE, b"\0")

    # -- requests ------------------------------------------------------------------------------------
    def open(self, info: FmuInfo, name: str, rollback: bool, folder: str, start_time: float = 0.0,
             period_ns: int = 1) -> tuple[int, int]:
        self.mark("load")
        self.session = s = Session(info, name, rollback=rollback, folder=folder, start_time=start_time)
        if s.events is not None:
            s.events.period_ns = period_ns
        s.api.on_call = self.mark
        self._code = ctypes.c_int32.from_buffer(self.trace, TRACE_SIZE)  # (kept: the helper writes there)
        s.stepper.trace_to(ctypes.addressof(self._code), self.mark)
        s.bind(np.zeros(s.n_in_all), np.zeros(s.n_out_all))
        return s.n_in_all, s.n_out_all

    def init(self, t0_ns: int, params: dict[str, Any], inputs: np.ndarray) -> tuple[np.ndarray, bytes | None]:
        s = self.session
        s.in_values[:] = inputs
        s.initialize(t0_ns / 1e9, params, origin_ns=t0_ns)
        return s.out_values.copy(), self._state(None)

    def attach(self, path: str, size: int) -> None:
        """Map the parent's step file (see the module docstring)."""
        s = self.session
        with open(path, "r+b") as fh:
            self.io = mmap.mmap(fh.fileno(), size)
        at = 8 * IO_HEADER
        self.head = np.ndarray(IO_HEADER, dtype=np.int64, buffer=self.io)
        self.io_address = self.head.ctypes.data  # the file's first byte
        self.io_in = np.ndarray(s.n_in_all, dtype=np.float64, buffer=self.io, offset=at)
        at += 8 * s.n_in_all
        self.io_out = np.ndarray(s.n_out_all, dtype=np.float64, buffer=self.io, offset=at)
        self.state_at = at + 8 * s.n_out_all

    def fast_step(self) -> None:
        """A step asked for through the step file: the state serialized straight into it."""
        head, s = self.head, self.session
        s.in_values[:] = self.io_in
        pool = s.pool
        state = s.step(int(head[0]), int(head[1]), pool is not None)
        self.io_out[:] = s.out_values
        self.last = None
        if pool is None or not s.info.can_serialize:
            head[2] = -2
            return
        if state is None:
            state = s.capture()
        self.keep = state
        room = int(head[3])
        if pool.aux is None:  # (a state with the clocks' schedule beside it is put together by the pool)
            n = s.api.serialize_into(int(pool.slots[state.slot]), self.io_address + self.state_at, room)
            if n <= room:
                head[2] = n
                return
        data = s.serialize(state).data
        if len(data) <= room:
            self.io[self.state_at:self.state_at + len(data)] = data
            head[2] = len(data)
        else:  # too long for the file: the parent asks `last_state`
            head[2], self.last = -1, data

    def last_state(self) -> bytes | None:
        return self.last

    def step(self, t_ns: int, dt_ns: int, inputs: np.ndarray) -> tuple[np.ndarray, bytes | None]:
        s = self.session
        s.in_values[:] = inputs
        state = s.step(t_ns, dt_ns, s.pool is not None)
        return s.out_values.copy(), self._state(state)

    def params(self, values: dict[str, Any], reinit: bool, t0_ns: int, all_params: dict[str, Any],
               inputs: np.ndarray) -> tuple[np.ndarray, bytes | None]:
        s = self.session
        if reinit:
            s.in_values[:] = inputs
            s.reinitialize(t0_ns / 1e9, all_params, origin_ns=t0_ns)
        else:
            s.set_params(values)
        return s.out_values.copy(), self._state(None)

    def set_state(self, token: str, data: bytes, outputs: np.ndarray | None = None, current: bool = False) -> None:
        """Restore a state; ``outputs``: the outputs on the parent's bus with it (clocked outputs hold
        their values between ticks, and are not read from the FMU at other steps); ``current``: the
        state of the last step (a request to end the simulation made there stands)."""
        asked = self.session.end_asked
        self.keep = self.session.restore(SerializedFMUState(token, data))
        if current:
            self.session.end_asked = asked
        if outputs is not None:
            self.session.out_values[:] = outputs

    def close(self) -> None:
        self.keep = None
        if self.io is not None:
            self.head = self.io_in = self.io_out = None
            self.io.close()
            self.io = None
        if self.session is not None:
            self.session.close()
            self.session = None

    def _state(self, state: FMUState | None) -> bytes | None:
        s = self.session
        if s.pool is None or not s.info.can_serialize:
            return None
        if state is None:
            state = s.capture()
        self.keep = state
        return s.serialize(state).data


def serve(conn: Connection, worker: Worker) -> None:
    while True:
        try:
            message = conn.recv_bytes()
        except (EOFError, OSError):
            break
        op = "step"
        try:
            if message == STEP:
                worker.fast_step()
                conn.send_bytes(DONE)
            else:
                op, *args = pickle.loads(message)  # our parent's request (a pipe of our own, never a peer's)
                conn.send(("ok", getattr(worker, op)(*args)))
        except ModuleError as exc:
            s = worker.session
            lost = s is not None and (s.api is None or s.api.dead or s.unusable is not None)
            conn.send(("error", type(exc).__name__, exc.call, str(exc.cause), lost, getattr(exc, "port", "")))
        except DynabrainError as exc:
            conn.send(("error", type(exc).__name__, None, str(exc), False, ""))
        except Exception as exc:
            conn.send(("error", "FMUError", None, f"{type(exc).__name__}: {exc}", False, ""))
        worker.mark("")
        if op == "close":
            break


def main(argv: list[str]) -> int:
    fd, trace_path = int(argv[1]), argv[2]
    with open(trace_path, "r+b") as fh:
        trace = mmap.mmap(fh.fileno(), TRACE_FILE_BYTES)
    worker = Worker(trace)
    conn = Connection(fd)
    try:
        serve(conn, worker)
    finally:
        worker.close()
        conn.close()
    return 0


if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the simulation, which stops this process itself
    sys.stdout = sys.stderr  # an FMU's prints and ours go to the log, never into the protocol
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    raise SystemExit(main(sys.argv))
