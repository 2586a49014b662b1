"""The FMU as a module: the facade the world sees.

Ports and parameters come from the model description (`info`). The module's capabilities are the
FMU's: it can roll back when the FMU declares ``canGetAndSetFMUstate`` and fork when it declares
``canSerializeFMUstate``; otherwise the kernel refuses backtick / fork naming the module.

Lifecycle: ``setup`` extracts, loads and instantiates the FMU; ``start`` sets the parameters,
initializes at the joining tick and writes the initial outputs; ``step`` is one ``DoStep`` of the
module's period, inputs read from and outputs written into the bus in place, the FMU state saved
for history in the same crossing into C; ``close`` terminates and frees (also after any failure).
A step the FMU discards or fails raises `FMUDiscardError` / `FMUCallError`; the world rolls back to
the last good tick (restoring the FMU's state) and reports module, call and tick. An FMU that cannot
restore its state (``canGetAndSetFMUstate`` false), or that reported a fatal error, cannot be used
after such a failure (the FMI standard allows only to reset or free it): every later step raises
`FMUUnusableError` naming it. One that asks to end the simulation raises `FMUTerminatedError`.

Time: the FMU's time is the world's plus its start time (``DefaultExperiment.startTime``, or
``start_time`` given to the module), so an FMU joining a world at t=0 starts where its description
says and its outputs line up with a simulation of it alone (FMPy's) row for row.
"""

from __future__ import annotations

import ctypes
import logging
import weakref
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ..kernel.errors import DynabrainError, UnitError
from ..kernel.module import Capabilities, Module, Param, Port, SetupContext
from .clocks import check_periods
from .errors import FMUCallError, FMUError
from .fused import FusedFMUs, GroupSerialized, GroupState, step_each
from .info import DIMENSIONS, FmuInfo, Signal
from .session import Session
from .states import FMUState, SerializedFMUState

if TYPE_CHECKING:
    from ..kernel.structure import Copies

_log = logging.getLogger("dynabrain.fmu")
_LISTED: set[str] = set()  # FMUs whose variables not on the bus were listed (once per process)


class BinaryParam(Param):
    """An FMI 3.0 Binary parameter: bytes, or text of hex digits (``"00ff"``)."""

    def convert(self, value: Any) -> Any:
        if isinstance(value, (bytes, bytearray)):
            return bytes(value)
        if isinstance(value, str):
            try:
                return bytes.fromhex(value)
            except ValueError:
                raise UnitError(f"expected bytes or hex digits, got {value!r}") from None
        raise UnitError(f"expected bytes or hex digits, got {value!r}")


def make_param(sig: Signal) -> Param:
    """A module parameter for an FMU parameter (vectors become lists)."""
    if sig.type == "binary":
        return BinaryParam(sig.name, sig.start[0], runtime=sig.tunable, doc=sig.description)
    if sig.type == "string":
        return Param(sig.name, sig.start[0], runtime=sig.tunable, doc=sig.description)
    cast = float if sig.type in ("real", "float32") else bool if sig.type == "boolean" else int
    default: Any = cast(sig.start[0]) if not sig.shape else tuple(cast(v) for v in sig.start)
    dimension = DIMENSIONS.get(sig.unit) if sig.type in ("real", "float32") else None
    return Param(sig.name, default, unit=sig.unit, runtime=sig.tunable, doc=sig.description, dimension=dimension)


def list_not_on_bus(info: FmuInfo) -> None:
    """Say once (per FMU, per process) which of its variables are not on the bus."""
    if info.skipped and info.path not in _LISTED:
        _LISTED.add(info.path)
        _log.warning("%s: not on the bus: %s", info.label, ", ".join(info.skipped))


def make_ports(signals: Sequence[Signal]) -> tuple[Port, ...]:
    """Block ports in order (starting at the FMU's start values), then a view port ``name[i]`` per
    element of each vector."""
    ports = [Port(s.name, s.shape, s.unit, s.description, start=_start(s)) for s in signals]
    for s in signals:
        if len(s.shape) == 1:
            ports += [Port(f"{s.name}[{i + 1}]", (), s.unit, view_of=(s.name, i)) for i in range(s.shape[0])]
    return tuple(ports)


def _start(sig: Signal) -> float | tuple[float, ...] | None:
    try:
        values = tuple(float(v) for v in sig.start)
    except (TypeError, ValueError):
        return None
    if not values:
        return None
    return values if sig.shape else values[0]


class FMUModuleBase(Module):
    """Ports, parameters and capabilities of an FMU (shared by the in-process and isolated modules)."""

    def __init__(self, name: str, info: FmuInfo, *, source: str = "", targets: Sequence[str] = (),
                 start_time: float | None = None, **params: Any):
        self.info = info
        self.source = source or info.path
        self.start_time = info.start_time if start_time is None else float(start_time)
        """The FMU's time at world time 0 (its time is the world's plus this)."""
        if not np.isfinite(self.start_time):
            raise DynabrainError(f"module {name!r}: start_time must be a finite number of seconds, got {start_time!r}")
        self._specs = {s.name: make_param(s) for s in info.params}
        self._inputs = make_ports(info.inputs)
        self._outputs = make_ports(info.outputs)
        self.CAPABILITIES = self.capabilities(info)
        super().__init__(name, targets=targets, **params)
        self._t0 = 0.0

    @staticmethod
    def capabilities(info: FmuInfo) -> Capabilities:
        # finite_outputs: the session checks the outputs as it reads them (in C on the fast path), raising
        # NonFiniteOutputError itself, so the world need not check them again
        return Capabilities(can_rollback=info.can_get_set, can_fork=info.can_serialize, feedthrough=info.feedthrough,
                            finite_outputs=False)

    def param_specs(self) -> dict[str, Param]:  # type: ignore[override]  # per instance: the FMU's parameters
        return self._specs

    def inputs(self) -> Sequence[Port]:
        return self._inputs

    def outputs(self) -> Sequence[Port]:
        return self._outputs

    def _spans(self) -> tuple[np.ndarray, np.ndarray, list, list]:
        """The flat input and output arrays: views of the bus when the ports lie side by side in it
        (they do: the bus lays a module's ports out in order), else buffers copied every step."""
        gather: list = []
        scatter: list = []
        ins = [self.inp[s.name] for s in self.info.inputs] if self.inp else []
        outs = [self.out[s.name] for s in self.info.outputs] if self.out else []
        n_in = sum(s.size for s in self.info.inputs)
        n_out = sum(s.size for s in self.info.outputs)
        in_values = _span(ins, n_in) if ins else None
        out_values = _span(outs, n_out) if outs else None
        if in_values is None:
            in_values = np.zeros(n_in)
            gather = _pieces(ins)
        if out_values is None:
            out_values = np.zeros(n_out)
            scatter = _pieces(outs)
        return in_values, out_values, gather, scatter

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        info = self.info
        out["fmu"] = {"source": self.source, "file": info.path, "fmi": f"{info.version}.0", "model": info.model_name,
                      "can_get_set_state": info.can_get_set, "can_serialize_state": info.can_serialize,
                      "start_time": self.start_time, "not_exposed": list(info.skipped)}
        return out

    def scenario_spec(self) -> dict[str, Any]:
        """The scenario syntax that makes this module again."""
        spec = {"name": self.name, "fmu": self.source, "params": self._plain_params()}
        if self.start_time != self.info.start_time:  # set by the scenario (start_time:), not the FMU's own
            spec["start_time"] = self.start_time
        return spec


def _span(views: list[np.ndarray], total: int) -> np.ndarray | None:
    start = views[0].ctypes.data
    at = 0
    for v in views:
        if v.ctypes.data != start + 8 * at or not v.flags.c_contiguous:
            return None
        at += v.size
    if at != total:
        return None
    return np.ctypeslib.as_array((ctypes.c_double * total).from_address(start))


def _pieces(views: list[np.ndarray]) -> list[tuple[np.ndarray, slice]]:
    out, at = [], 0
    for v in views:
        out.append((v, slice(at, at + v.size)))
        at += v.size
    return out


class FMUModule(FMUModuleBase):
    """An FMU stepped in the world's process. See the module docstring."""

    def __init__(self, name: str, info: FmuInfo, *, source: str = "", targets: Sequence[str] = (),
                 start_time: float | None = None, **params: Any):
        super().__init__(name, info, source=source, targets=targets, start_time=start_time, **params)
        self._session: Session | None = None
        self._state: FMUState | GroupState | SerializedFMUState | None = None
        self._dt_ns = 0
        self._fused: FusedFMUs | None = None  # the group that steps this module with others, if any
        self._group_pools: weakref.WeakSet = weakref.WeakSet()  # groups' state pools with states of ours
        self._unbind()

    def _unbind(self) -> None:
        self._pool = None
        self._fn: Any = None
        self._arg = 0
        self._gather: list = []
        self._scatter: list = []
        self._simple = False
        self._views: tuple[Mapping[str, np.ndarray], Mapping[str, np.ndarray]] = ({}, {})

    # -- lifecycle -------------------------------------------------------------------------------------
    def setup(self, ctx: SetupContext) -> None:
        self._dt_ns = ctx.period_ns
        check_periods(self.info.clocks, ctx.period_ns, self.name)
        self._session = Session(self.info, self.name, rollback=self.CAPABILITIES.can_rollback,
                                start_time=self.start_time)
        if self._session.events is not None:
            self._session.events.period_ns = ctx.period_ns
        self._pool = self._session.pool
        self.bind()

    def bind(self) -> None:
        session = self._session
        if session is None:
            return
        in_values, out_values, self._gather, self._scatter = self._spans()
        session.bind(in_values, out_values)
        self._views = (self.inp, self.out)  # the session holds addresses into these buffers
        self._fn, self._arg = session.stepper.fn, session.stepper.arg
        self._simple = self._hot(session)
        if session.stepper.dt_ns != self._dt_ns:
            session.stepper.set_step(self._dt_ns)
        self._fused_stale()

    def _hot(self, session: Session) -> bool:
        """Whether `step` takes its hot path: reals on the bus, states for history, nothing pending."""
        return (self._pool is not None and not self._gather and not self._scatter and not session.in_typed
                and not session.out_typed and session.events is None and session.end_asked is None)

    @classmethod
    def fuse(cls, members: Sequence[Module], copies: Sequence[Copies]) -> FusedFMUs | None:
        """A chain of FMU modules next to each other in the schedule steps in one call into the C
        helper (`orchestrator.fmu.fused`) while they all take the hot path of `step`."""
        if cls is not FMUModule or any(type(m) is not FMUModule for m in members):
            return None
        return FusedFMUs.make(members, copies)  # type: ignore[arg-type]

    @classmethod
    def step_batch(cls, members: Sequence[Module], t_ns: int, dt_ns: int, inp: np.ndarray, out: np.ndarray,
                   failed: dict[int, BaseException]) -> None:
        """The N instances of one FMU (N branches of a lockstep batch) stepped in one call into the C
        helper (`fused.step_each`) when each takes the hot path of `step` (reals on the bus): the same
        FMI calls per instance as its own step, less the state it saves for history (a lockstep keeps
        none; `get_state` takes one when asked). Otherwise each member steps on its own."""
        fmus: list[FMUModule] = list(members)  # type: ignore[arg-type]
        if cls is not FMUModule or not all(type(m) is FMUModule and m._simple and dt_ns == m._dt_ns and m._fusable()
                                            for m in fmus) or not step_each(fmus, t_ns, failed):
            super().step_batch(members, t_ns, dt_ns, inp, out, failed)
            return
        for m in fmus:
            m._state = None  # the FMU's state now is not the one its last step saved

    def _fusable(self) -> bool:
        """Whether `step` would take its hot path (with or without states for history) on the C helper."""
        session = self._session
        if session is None or not session.stepper.fast or session.api is None or session.api.dead:
            return False
        return (session.unusable is None and not self._gather and not self._scatter and not session.in_typed
                and not session.out_typed and session.events is None and session.end_asked is None)

    def _fused_stale(self) -> None:
        """Whether this module can be stepped with others changed: its group looks again."""
        if self._fused is not None:
            self._fused.ok = None

    def start(self, t_ns: int) -> None:
        session = self._require("start")
        self._t0 = t_ns / 1e9
        self._copy_in()
        session.initialize(self._t0, dict(self.params), origin_ns=t_ns)
        self._copy_out()
        self._state = session.capture() if self._pool is not None else None

    def step(self, t_ns: int, dt_ns: int) -> None:
        pool = self._pool
        if self._simple and dt_ns == self._dt_ns:  # the hot path: reals on the bus, states for history
            free = pool.free
            slot = free.pop() if free else pool.take()
            rc = self._fn(self._arg, t_ns, pool.base + 8 * slot)
            if rc:
                self._failed(rc, slot, t_ns)
            self._state = FMUState(pool, slot)
            return
        session = self._require("step")
        self._dt_ns = dt_ns
        if self._gather:
            self._copy_in()
        state = session.step(t_ns, dt_ns, pool is not None)
        if pool is not None:
            self._state = state
        if self._scatter:
            self._copy_out()

    def _failed(self, rc: int, slot: int, t_ns: int) -> None:
        session = self._session
        try:
            session.failed(rc, slot, t_ns)
        finally:
            if session.api.dead or session.unusable is not None or session.end_asked is not None:
                self._simple = False  # the general path refuses to call an instance that failed for good
                self._fused_stale()  # (or raises the end the FMU asked for)

    def _copy_in(self) -> None:
        values = self._session.in_values
        for view, where in self._gather:
            values[where] = view.reshape(-1)

    def _copy_out(self) -> None:
        values = self._session.out_values
        for view, where in self._scatter:
            view.reshape(-1)[...] = values[where]

    def _require(self, call: str) -> Session:
        if self._session is None:
            raise FMUError(f"module {self.name!r}: {call}() before setup (or after close)")
        return self._session

    # -- state -----------------------------------------------------------------------------------------
    def get_state(self) -> FMUState | SerializedFMUState | None:
        state = self._state
        if state is None and self._pool is not None:
            state = self._state = self._pool.capture()
        return state

    def set_state(self, state: Any) -> None:
        session = self._require("set_state")
        if session.end_asked is not None and state is not self._state:  # from before the step that asked to end
            session.end_asked = None  # (the world's rollback of the tick that raised it restores the current one)
            self._simple = self._hot(session)
            self._fused_stale()
        if session.api is None or session.api.dead:
            self._state = state  # nothing can be restored into a dead instance; the next step says so
            return
        try:
            if isinstance(state, GroupState):  # the state of a tick stepped with other FMUs (`fused`)
                handle = state.handle(self)
                if handle is not None:
                    session.api.set_state(handle)
                    session.unusable = None
                    self._state = state
                    return
                state = state.serialized(self.name)  # of another instance: a fork's original
            elif isinstance(state, GroupSerialized):
                state = state.of(self.name)
            if state is self._state and isinstance(state, FMUState):
                session.pool.restore(state)
                session.unusable = None
                return
            self._state = session.restore(state)
        except (FMUError, FMUCallError, KeyError) as exc:  # the world is rolling back: never leave it half done
            self._state = state
            self._simple = False
            self._fused_stale()
            session.unusable = (f"{self.info.label}: restoring its state failed ({exc}); the FMI standard allows "
                                "only to reset or free it now. Remove the module or load the world again")
            _log.warning("module %r: %s", self.name, session.unusable)

    def on_param(self, name: str, value: Any) -> None:
        session = self._session
        if session is None or not session.initialized or session.unusable is not None or session.api.dead:
            return
        if self._specs[name].runtime:
            session.set_params({name: value})
        else:
            self._copy_in()
            session.reinitialize(self._t0, dict(self.params))
            self._copy_out()
        self._state = None

    def close(self) -> None:
        for pool in list(self._group_pools):
            pool.close_member(self)  # the handles go before the instance does
        session, self._session = self._session, None
        self._state = None
        self._unbind()
        if session is not None:
            session.close()

    def fork(self, memo: dict[int, Any]) -> FMUModule:
        """A fork: a new instance of the FMU in the same state (through its serialized state)."""
        clone = FMUModule(self.name, self.info, source=self.source, targets=self.targets, start_time=self.start_time)
        clone.adopt_param_state(self.param_state())
        memo[id(self)] = clone
        if self._session is None:
            return clone
        state = self.get_state()
        state = state.serialized(self.name) if isinstance(state, GroupState) else self._session.serialize(state)
        clone._session = Session(self.info, self.name, rollback=clone.CAPABILITIES.can_rollback,
                                 start_time=self.start_time)
        if clone._session.events is not None:
            clone._session.events.period_ns = self._session.events.period_ns
        clone._pool = clone._session.pool
        clone._t0, clone._dt_ns = self._t0, self._dt_ns
        try:
            self._copy_in()
            clone._session.in_values[:] = self._session.in_values  # valid inputs (an enumeration takes no 0)
            clone._session.initialize(self._t0, dict(self.params))
            clone._state = clone._session.restore(state)
        except BaseException:
            clone.close()
            raise
        return clone
