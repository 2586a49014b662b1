"""An FMU in a process of its own (``isolate: true``): a crash is a reported failure, not the end.

The module runs a `worker` child and talks to it over a socket pair: inputs in, outputs and the
serialized FMU state out, once per step. If the FMU kills its process (a segfault, an abort), the
step raises `FMUCrashError` naming the module, the FMI call that was running, the signal and the
child's last output; the world rolls back to the last good tick (the kernel does that for any
failed step) and hands this module that tick's state. The next step starts a fresh process,
instantiates the FMU and restores that state, so the world goes on. A fatal error, or a failure the
FMU cannot undo (see `session`: unusable), ends its process the same way.

An FMU that cannot serialize its state has none here to come back to: the next step restarts it from
scratch (instantiated and initialized at that tick, with the current parameters and inputs), and the
failing step's error and a warning of the ``dynabrain.fmu`` logger say that its state was lost;
`restarts` lists each restart.

The state lives in this process as bytes (`SerializedFMUState`), so the module can roll back and
fork when the FMU can serialize its state, and neither when it cannot.
"""

from __future__ import annotations

import contextlib
import logging
import mmap
import os
import pickle
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path
from time import perf_counter
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError, NonFiniteOutputError
from ..kernel.module import Capabilities, SetupContext
from ..kernel.workers import spawn_worker
from . import errors as fmu_errors
from .clocks import check_periods
from .errors import FMUCrashError, FMUError, FMUTimeoutError
from .fastpath import CALLS
from .info import FmuInfo
from .module import FMUModuleBase
from .states import SerializedFMUState
from .worker import DONE, IO_HEADER, STEP, TRACE_FILE_BYTES, TRACE_SIZE

_log = logging.getLogger("dynabrain.fmu")
STATE_BYTES = 1 << 16
"""Room for the serialized state in the step file (`worker`); a longer state crosses the pipe."""
STOP_TIMEOUT_S = 5.0
SPIN_S = 100e-6
"""How long a step waits for the child's answer awake (polling the socket without sleeping) before it
sleeps until the answer comes: a process woken from sleep by the answer takes tens of microseconds
more. On this 2-core machine a step of the passthrough FMU took 56 us sleeping and 28 us awake
(`bench/fmu_chain.py`; a bare one-byte ping-pong between two processes: 47 us and 20 us). A step
longer than this costs this much of a core more, spent waiting."""
CALL_TIMEOUT_S = 30.0
"""How long one call of an isolated FMU may take by default (``call_timeout`` in a scenario)."""
START_TIMEOUT_S = 60.0
"""How long starting the child and loading the FMU may take, at least (Python and FMPy start first;
on a busy machine that is slow, so ``call_timeout`` does not bound it)."""


class _Child:
    """One worker process: its connection, its folder (log, trace of the FMI call under way, the
    extracted FMU), removed here even when the process dies."""

    def __init__(self, label: str):
        self.dir = Path(tempfile.mkdtemp(prefix="dynabrain-isolated-"))
        self.log_path = self.dir / "worker.log"
        trace_path = self.dir / "trace"
        trace_path.write_bytes(b"\0" * TRACE_FILE_BYTES)
        with open(trace_path, "r+b") as fh:
            self.trace = mmap.mmap(fh.fileno(), TRACE_FILE_BYTES)
        self.log = open(self.log_path, "wb")  # noqa: SIM115 - open for the child's whole life
        self.log_fd = self.log.fileno()
        self.since = 0
        """Where the child's output of the current request begins in its log (the file's offset, which
        the child's writes move: they share the open file)."""
        try:
            self.proc, self.conn = spawn_worker("dynabrain.orchestrator.fmu.worker", str(trace_path), stdout=self.log,
                                                stderr=subprocess.STDOUT)
        except OSError as exc:
            self.cleanup()
            raise FMUError(f"{label}: cannot start the isolation process: {exc}") from None

    def call_in_progress(self, version: int) -> str:
        """The FMI call the child was in ("" when it was between requests): the C step helper's, else
        the one Python made (`worker`)."""
        code = int.from_bytes(self.trace[TRACE_SIZE:TRACE_SIZE + 4], "little")
        if code in CALLS[version]:
            return CALLS[version][code]
        return bytes(self.trace[:TRACE_SIZE]).rstrip(b"\0").decode("ascii", "replace")

    def death(self) -> str:
        """How the process ended (waits for it briefly), and the end of its log."""
        try:
            rc = self.proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        if rc < 0:
            try:
                how = f"killed by {signal.Signals(-rc).name}"
            except ValueError:
                how = f"killed by signal {-rc}"
        else:
            how = f"exited with status {rc}"
        self.log.flush()
        with open(self.log_path, "rb") as fh:  # only what it wrote since the request began
            fh.seek(self.since)
            tail = fh.read()[-1500:].decode("utf-8", "replace").strip()
        lines = [ln for ln in tail.splitlines() if ln.strip()][-6:]
        return how + ("; its output in this call: " + " | ".join(lines) if lines else "")

    def mark_log(self) -> None:
        """A request begins: its output starts here."""
        self.since = os.lseek(self.log_fd, 0, os.SEEK_CUR)

    def stop(self) -> None:
        with contextlib.suppress(Exception):
            self.conn.send(("close",))
            if self.conn.poll(STOP_TIMEOUT_S):
                self.conn.recv()
        with contextlib.suppress(Exception):
            self.proc.wait(STOP_TIMEOUT_S)
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.cleanup()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self.cleanup()

    def attach(self, n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Make the step file (`worker`'s docstring): (its header, inputs and outputs as arrays, where
        the state's bytes start); the child maps it with the request ``attach``."""
        at = 8 * (IO_HEADER + n_in + n_out)
        path = self.dir / "io"
        path.write_bytes(b"\0" * (at + STATE_BYTES))
        with open(path, "r+b") as fh:
            self.io = mmap.mmap(fh.fileno(), at + STATE_BYTES)
        head = np.ndarray(IO_HEADER, dtype=np.int64, buffer=self.io)
        head[3] = STATE_BYTES
        ins = np.ndarray(n_in, dtype=np.float64, buffer=self.io, offset=8 * IO_HEADER)
        outs = np.ndarray(n_out, dtype=np.float64, buffer=self.io, offset=8 * (IO_HEADER + n_in))
        return head, ins, outs, at

    def cleanup(self) -> None:
        for closer in (getattr(self, "conn", None), self.trace, self.log):
            with contextlib.suppress(Exception):
                if closer is not None:
                    closer.close()
        io = getattr(self, "io", None)
        if io is not None:
            with contextlib.suppress(BufferError):  # arrays on it still alive: the mapping goes with them
                io.close()
        shutil.rmtree(self.dir, ignore_errors=True)  # the log, the trace and the extracted FMU


class IsolatedFMUModule(FMUModuleBase):
    """An FMU module whose FMU runs in a child process. See the module docstring."""

    def __init__(self, name: str, info: FmuInfo, *, source: str = "", targets: Sequence[str] = (),
                 call_timeout: float = CALL_TIMEOUT_S, start_time: float | None = None, **params: Any):
        super().__init__(name, info, source=source, targets=targets, start_time=start_time, **params)
        if not call_timeout > 0:
            raise FMUError(f"module {name!r}: call_timeout must be a positive duration, got {call_timeout!r}")
        self.call_timeout = float(call_timeout)
        """Seconds one call (a step, a state transfer) may take before the process is killed."""
        self._child: _Child | None = None
        self._state: SerializedFMUState | None = None
        self._pending: SerializedFMUState | None = None
        self._started = False
        self._period_ns = 1
        self.restarts: list[str] = []
        """Each restart from scratch (its state lost), as the warning said it."""
        self._t0_ns = 0
        self._bind_buffers()

    @staticmethod
    def capabilities(info: FmuInfo) -> Capabilities:
        return Capabilities(can_rollback=info.can_serialize, can_fork=info.can_serialize,
                            feedthrough=info.feedthrough)  # the world checks the outputs are finite

    # -- the child -------------------------------------------------------------------------------------
    def _spawn(self) -> None:
        """Start a worker and load the FMU in it; on any failure no process is left behind."""
        self._child = _Child(self.info.label)
        try:
            n_in, n_out = self._request("open", self.info, self.name, self.CAPABILITIES.can_rollback,
                                        str(self._child.dir / "fmu"), self.start_time, self._period_ns,
                                        timeout=max(self.call_timeout, START_TIMEOUT_S))
            self._io = self._child.attach(n_in, n_out)
            self._request("attach", str(self._child.dir / "io"), len(self._child.io))
        except BaseException:
            child, self._child = self._child, None
            if child is not None:
                child.kill()
            raise

    def _request(self, op: str, *args: Any, timeout: float | None = None) -> Any:
        """One request to the child, answered within ``timeout`` (default: ``call_timeout``)."""
        child = self._child
        if child is None:
            raise FMUCrashError(self.name, op, None, "the FMU process is not running")
        try:
            child.mark_log()
            child.conn.send((op, *args))
            if not child.conn.poll(self.call_timeout if timeout is None else timeout):
                raise self._hung(op, self.call_timeout if timeout is None else timeout)
            reply = child.conn.recv()
        except (EOFError, OSError) as exc:
            raise self._crashed(op, exc) from None
        if reply[0] == "ok":
            return reply[1]
        self._refused(reply)

    def _step_request(self, t_ns: int, dt_ns: int) -> None:
        """A step through the step file (`worker`): time and inputs in, outputs and state out."""
        child = self._child
        head, ins, outs, state_at = self._io
        head[0], head[1] = t_ns, dt_ns
        ins[:] = self._gather_inputs()
        try:
            conn = child.conn
            child.mark_log()
            conn.send_bytes(STEP)
            end = perf_counter() + SPIN_S  # wait awake a little: a step is often back by then
            while not conn.poll(0):
                if perf_counter() > end:
                    if not conn.poll(self.call_timeout):
                        raise self._hung("step", self.call_timeout)
                    break
            reply = conn.recv_bytes()
        except (EOFError, OSError) as exc:
            raise self._crashed("step", exc) from None
        if reply != DONE:
            self._refused(pickle.loads(reply))  # our child's error reply (a pipe of our own)
        self._write_outputs(outs)
        n = int(head[2])
        if n >= 0:
            self._state = SerializedFMUState(self.info.token, child.io[state_at:state_at + n])
        else:
            self._state = None if n == -2 else self._as_state(self._request("last_state"))

    def _refused(self, reply: tuple) -> None:
        """Raise the error a child's reply carries."""
        _, kind, call, message, lost, port = reply
        if lost:  # fatal, or failed without a way back: a new process takes over from the last good state
            self._drop_child()
            message += self._next_start()
        if call is None:
            raise FMUError(message) if kind == "FMUError" else DynabrainError(message)
        if kind == "NonFiniteOutputError":
            raise NonFiniteOutputError(self.name, call, None, message, port)
        cls = getattr(fmu_errors, kind, fmu_errors.FMUCallError)
        raise cls(self.name, call, None, message)

    def _crashed(self, op: str, exc: BaseException) -> FMUCrashError:
        call, how = self._lose_child("died")
        during = f"during {call}" if call else "between two calls"
        return FMUCrashError(self.name, call or op, None, f"the isolated FMU process died {during} ({op}): {how}; "
                             f"{self.info.label}{self._next_start()}")

    def _hung(self, op: str, timeout: float) -> FMUTimeoutError:
        """The child did not answer in time: kill it; the next step starts a new one from the last good
        state, as after a crash."""
        self._child.proc.kill()
        call, how = self._lose_child(f"was killed (no answer within {timeout:g} s)")
        return FMUTimeoutError(self.name, call or op, None, f"the isolated FMU did not answer within "
                               f"{timeout:g} s ({'in ' + call if call else op}); its process was "
                               f"killed ({how}); {self.info.label}{self._next_start()}")

    def _next_start(self) -> str:
        """What the next step does, for the error of a step that lost the process."""
        if self._pending is not None:
            return "; the next step restarts it from the last good state"
        return (f"; its state is lost ({self.info.label} cannot serialize it): the next step restarts it from "
                "scratch")

    def _lose_child(self, what: str) -> tuple[str, str]:
        """Forget a dead child: (the FMI call it was in, how it ended). The next step starts a new one
        from the last good state, or from scratch when there is none."""
        child = self._child
        call = child.call_in_progress(self.info.version)
        how = child.death()
        self._child = None
        child.cleanup()
        self._pending = self._state
        return call, how

    def _drop_child(self) -> None:
        child, self._child = self._child, None
        if child is not None:
            child.kill()
        self._pending = self._state

    def _revive(self, t_ns: int) -> None:
        """A fresh process at the state of the last good tick, or from scratch at ``t_ns`` when the FMU
        has no state to come back to (it cannot serialize it)."""
        self._spawn()
        if self._pending is None:
            outputs, state = self._request("init", t_ns, dict(self.params), self._inputs_now())
            self._write_outputs(outputs)
            self._state = self._as_state(state)
            note = (f"module {self.name!r}: {self.info.label} was restarted from scratch at t={t_ns / 1e9:g} s "
                    f"(world time): its state before was lost (it cannot serialize it)")
            self.restarts.append(note)
            _log.warning("%s", note)
            return
        self._request("init", self._t0_ns, dict(self.params), self._inputs_now())
        self._request("set_state", self._pending.token, self._pending.data, self._outputs_now())
        self._state, self._pending = self._pending, None

    # -- values ----------------------------------------------------------------------------------------
    def _bind_buffers(self) -> None:
        self._in_values, self._out_values, self._gather, self._scatter = self._spans()

    def _gather_inputs(self) -> np.ndarray:
        """The inputs now, gathered from the bus into ``_in_values`` (which this returns)."""
        for view, where in self._gather:
            self._in_values[where] = view.reshape(-1)
        return self._in_values

    def _inputs_now(self) -> np.ndarray:
        """A copy of the inputs now, for a request."""
        return np.array(self._gather_inputs(), dtype=np.float64)

    def _outputs_now(self) -> np.ndarray:
        """The outputs on the bus: after a restore, the values clocked outputs hold until their next tick."""
        for view, where in self._scatter:
            self._out_values[where] = view.reshape(-1)
        return np.array(self._out_values, dtype=np.float64)

    def _write_outputs(self, values: np.ndarray) -> None:
        self._out_values[:] = values
        for view, where in self._scatter:
            view.reshape(-1)[...] = values[where]

    # -- lifecycle -------------------------------------------------------------------------------------
    def setup(self, ctx: SetupContext) -> None:
        check_periods(self.info.clocks, ctx.period_ns, self.name)
        self._period_ns = ctx.period_ns
        self._spawn()

    def bind(self) -> None:
        self._bind_buffers()

    def start(self, t_ns: int) -> None:
        self._t0_ns = t_ns
        outputs, state = self._request("init", t_ns, dict(self.params), self._inputs_now())
        self._write_outputs(outputs)
        self._state = self._as_state(state)
        self._started = True

    def step(self, t_ns: int, dt_ns: int) -> None:
        if self._child is None:
            self._revive(t_ns)
        self._step_request(t_ns, dt_ns)

    def _as_state(self, data: bytes | None) -> SerializedFMUState | None:
        return None if data is None else SerializedFMUState(self.info.token, data)

    def get_state(self) -> SerializedFMUState | None:
        return self._state

    def set_state(self, state: Any) -> None:
        if not isinstance(state, SerializedFMUState):
            raise FMUError(f"module {self.name!r}: {state!r} is not a state of an isolated FMU")
        current, self._state = self._state, state
        if self._child is None:
            self._pending = state
            return
        try:  # (the current state again: a request to end the simulation made in its step stands)
            self._request("set_state", state.token, state.data, self._outputs_now(), state is current)
        except DynabrainError as exc:  # the world is rolling back: never leave it half done
            if self._child is not None:
                self._drop_child()
            self._pending = state  # restored when the next step starts a new process
            _log.warning("module %r: restoring the FMU's state failed (%s); the next step restarts it", self.name, exc)

    def on_param(self, name: str, value: Any) -> None:
        if self._child is None or not self._started:
            return
        reinit = not self._specs[name].runtime
        outputs, state = self._request("params", {name: value}, reinit, self._t0_ns, dict(self.params),
                                       self._inputs_now())
        if reinit:
            self._write_outputs(outputs)
        self._state = self._as_state(state)

    def close(self) -> None:
        child, self._child = self._child, None
        if child is not None:
            child.stop()

    def scenario_spec(self) -> dict[str, Any]:
        spec = {**super().scenario_spec(), "isolate": True}
        if self.call_timeout != CALL_TIMEOUT_S:
            spec["call_timeout"] = self.call_timeout
        return spec

    @property
    def pid(self) -> int | None:
        """The child's process id (None while no process runs)."""
        return self._child.proc.pid if self._child is not None else None

    def fork(self, memo: dict[int, Any]) -> IsolatedFMUModule:
        """A fork: a new process, initialized and set to this module's state."""
        clone = IsolatedFMUModule(self.name, self.info, source=self.source, targets=self.targets,
                                  call_timeout=self.call_timeout, start_time=self.start_time)
        clone.adopt_param_state(self.param_state())
        clone._t0_ns, clone._started, clone._period_ns = self._t0_ns, self._started, self._period_ns
        memo[id(self)] = clone
        if self._child is None and self._pending is None:
            return clone
        state = self._state
        clone._spawn()
        try:
            clone._request("init", self._t0_ns, dict(self.params), self._inputs_now())
            if state is not None:
                clone._request("set_state", state.token, state.data, self._outputs_now())
            clone._state = state
        except BaseException:
            clone.close()
            raise
        return clone

    def __del__(self) -> None:
        child = getattr(self, "_child", None)
        if child is not None and child.proc.poll() is None:
            with contextlib.suppress(Exception):
                child.kill()
