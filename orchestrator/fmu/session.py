"""One FMU instance at run time: extracted, loaded, instantiated, initialized, stepped, freed.

`FMUModule` drives a session in the world's process; the isolation worker drives one in a child
process. A session exchanges values through two flat float64 arrays bound with `bind`: every input
and every output in port order (reals first, then each other kind in `info.BUS_KINDS` order). The
reals go to and from the FMU in one call each; every other kind is converted around it, exactly: an
input that does not fit its type (300 for an Int8, 2.5e9 for an Int32, beyond 2^53 for a 64-bit
integer, NaN for an integer) and a 64-bit output beyond 2^53 fail the step naming the variable.

Failures follow the FMI standard. A step that fails (``Discard``, ``Error``, ``Fatal``, a terminate
request) leaves the instance in a state only a restored FMU state can undo: a session without one
(the FMU cannot get and set its state) becomes *unusable* (``unusable`` says why), and so does one
after a fatal error; every later step raises `FMUUnusableError`, and `close` frees it without
calling ``Terminate``.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..kernel.errors import ModuleError, NonFiniteOutputError
from .api import FmuApi, make_api
from .errors import FMUCallError, FMUError, FMUTerminatedError, FMUUnusableError
from .events import Events
from .fastpath import CALLS, EARLY_RETURN, ENDED, NONFINITE, TERMINATE, Stepper, decode
from .info import BUS_KINDS, EXACT, INT_RANGES, FmuInfo, Signal
from .states import FMUState, SerializedFMUState, StatePool

FLOAT32_MAX = float(np.finfo(np.float32).max)
MAX_EARLY_RETURNS = 1000
"""Early returns from one step before the FMU is said not to get on."""
_WHAT_NOW = ("Remove the module (world.remove_module) or load the world again; with isolate: true it is restarted "
             "from scratch")
_FMI_TYPE = {"real": "Float64", "float32": "Float32", "int8": "Int8", "uint8": "UInt8", "int16": "Int16",
             "uint16": "UInt16", "integer": "Int32", "uint32": "UInt32", "int64": "Int64", "uint64": "UInt64",
             "boolean": "Boolean"}


@dataclass(frozen=True)
class Group:
    """Variables of one kind in one direction: their value references, their place in the flat array
    (a slice, or the positions of clocked variables), the FMU-typed buffer they go through, and each
    value's variable name."""

    kind: str
    vrs: np.ndarray
    where: slice | np.ndarray
    buf: np.ndarray
    names: tuple[str, ...]


def _vrs(signals: list[Signal]) -> np.ndarray:
    return np.array([vr for s in signals for vr in s.vrs], dtype=np.uint32)


def _names(signals: list[Signal]) -> tuple[str, ...]:
    return tuple(s.name if not s.shape else f"{s.name}[{i + 1}]" for s in signals for i in range(s.size))


def _typed(api: FmuApi, signals: list[Signal]) -> tuple[int, list[Group]]:
    """(number of real values, the groups of other kinds after them) of ``signals``, laid out in
    `BUS_KINDS` order from the start of the flat array."""
    n_real = sum(s.size for s in signals if s.type == "real")
    groups, at = [], n_real
    for kind in BUS_KINDS[1:]:
        sigs = [s for s in signals if s.type == kind]
        n = sum(s.size for s in sigs)
        if n:
            groups.append(Group(kind, _vrs(sigs), slice(at, at + n), np.zeros(n, dtype=api.DTYPES[kind]),
                                _names(sigs)))
        at += n
    return n_real, groups


def groups_at(api: FmuApi, signals: list[tuple[Signal, int]]) -> list[Group]:
    """Groups by kind (reals too) of ``signals``, each with its first position in the flat array."""
    out = []
    for kind in BUS_KINDS:
        sigs = [(s, at) for s, at in signals if s.type == kind]
        if sigs:
            where = np.array([at + i for s, at in sigs for i in range(s.size)], dtype=np.intp)
            out.append(Group(kind, _vrs([s for s, _ in sigs]), where, np.zeros(len(where), dtype=api.DTYPES[kind]),
                             _names([s for s, _ in sigs])))
    return out


def _step_flags(flags: np.ndarray) -> tuple[bool, bool, bool, float]:
    """FMI 3.0 DoStep's out arguments as the steppers keep them (bytes: eventHandlingNeeded,
    terminateSimulation, earlyReturn; lastSuccessfulTime at byte 24)."""
    return bool(flags[0]), bool(flags[1]), bool(flags[2]), float(flags[24:32].view(np.float64)[0])


def unclocked(signals: tuple[Signal, ...]) -> list[Signal]:
    """The signals set and read at every step (not clocked variables, not clock ports)."""
    return [s for s in signals if not s.clocks]


class Session:
    """A loaded and instantiated FMU. ``rollback``: keep states (a `StatePool`) for history;
    ``folder``: where to extract the FMU (default: a temporary folder removed at `close`);
    ``start_time``: the FMU's time at world time 0 (its time is the world's plus this)."""

    def __init__(self, info: FmuInfo, name: str, *, rollback: bool, folder: str | None = None,
                 start_time: float = 0.0):
        self.info, self.name = info, name
        if folder is not None:  # a folder its owner removes (isolation: even when this process dies)
            os.makedirs(folder, exist_ok=True)
        self.dir = folder or tempfile.mkdtemp(prefix="dynabrain-fmu-")
        self._remove_dir = weakref.finalize(self, shutil.rmtree, self.dir, True)  # also if never closed
        self.api: FmuApi | None = None
        self.initialized = False
        self.unusable: str | None = None
        """Why the instance cannot be used any more (None while it can)."""
        self.end_asked: str | None = None
        """FMI 3.0: the FMU asked to end the simulation in a step that succeeded. That step stands (FMI 3.0
        and FMPy keep it); the next step raises `FMUTerminatedError` with this message instead of
        stepping, until a state from before is restored."""
        try:
            _extract(info, self.dir)
            self.api = make_api(info, self.dir, name)
            self.api.instantiate()
        except BaseException:
            self.close()
            raise
        api = self.api
        self.n_in, self.in_typed = _typed(api, unclocked(info.inputs))
        self.n_out, self.out_typed = _typed(api, unclocked(info.outputs))
        self.n_in_all = sum(s.size for s in info.inputs)
        self.n_out_all = sum(s.size for s in info.outputs)
        real_in = [s for s in unclocked(info.inputs) if s.type == "real"]
        real_out = [s for s in unclocked(info.outputs) if s.type == "real"]
        self.stepper = Stepper(api, _vrs(real_in), self.n_in, _vrs(real_out), self.n_out,
                               no_prior=not (rollback and info.can_get_set))  # no state: no step is redone
        self.stepper.set_start_time(start_time)
        self.pool = StatePool(api) if rollback and info.can_get_set else None
        self.params = {s.name: s for s in info.params}
        self.events = Events(self) if info.clocks else None
        """Event mode and clocks (FMI 3.0 clocks; see `clocks`), or None."""
        if self.events is not None:
            self.stepper.use_python()  # it keeps DoStep's eventHandlingNeeded
            if self.pool is not None and self.events.schedule is not None:
                self.pool.aux = self.events.schedule  # the clocks' schedule is state: saved with the FMU's
        self.bind(np.zeros(self.n_in_all), np.zeros(self.n_out_all))

    @property
    def start_time(self) -> float:
        return self.stepper.t0

    # -- values --------------------------------------------------------------------------------------
    def bind(self, in_values: np.ndarray, out_values: np.ndarray) -> None:
        """Read inputs from ``in_values`` and write outputs to ``out_values`` (float64, contiguous,
        every input / output in port order)."""
        self.in_values, self.out_values = in_values, out_values
        self.stepper.bind(in_values, out_values)

    def write_typed_inputs(self) -> None:
        for g in self.in_typed:
            self.write_group(g)

    def write_group(self, g: Group) -> None:
        """Set the inputs of ``g`` from the flat array, converted to their type (refused, naming the
        variable, when a value does not fit)."""
        values = self.in_values[g.where]
        if g.kind == "real":
            g.buf[...] = values
        elif g.kind == "boolean":
            g.buf[...] = values != 0
        elif g.kind == "float32":
            if not np.all(np.abs(values) <= FLOAT32_MAX):
                self._refuse_input(g, values, ~(np.abs(values) <= FLOAT32_MAX), "is beyond the range of a Float32")
            g.buf[...] = values
        else:
            whole = np.rint(values)
            low, high = INT_RANGES[g.kind]
            fits = (whole >= max(low, -EXACT)) & (whole <= min(high, EXACT))
            if not fits.all():
                self._refuse_input(g, values, ~fits, f"does not fit {_FMI_TYPE[g.kind]} ({max(low, -EXACT)} to "
                                   f"{min(high, EXACT)})")
            g.buf[...] = whole
        try:
            self.api.set_values(g.kind, g.vrs, g.buf)
        except FMUCallError as exc:  # the FMU's own status (a refused value above is not the FMU's)
            self._failed_call(exc, 3)
            raise

    def _refuse_input(self, g: Group, values: np.ndarray, bad: np.ndarray, why: str) -> None:
        k = int(np.flatnonzero(bad)[0])
        raise FMUCallError(self.name, f"fmi{self.info.version}Set{_FMI_TYPE[g.kind]}", None,
                           f"input {g.names[k]} = {float(values[k]):g} {why}; {self.info.label}")

    def read_typed_outputs(self) -> None:
        for g in self.out_typed:
            self.read_group(g)

    def read_group(self, g: Group) -> None:
        """Get the outputs of ``g`` into the flat array (a 64-bit one beyond 2^53, or a float not
        finite, raises naming it)."""
        self.api.get_values(g.kind, g.vrs, g.buf)
        if g.kind in ("int64", "uint64") and np.any(np.abs(g.buf.astype(np.float64)) > EXACT):
            k = int(np.flatnonzero(np.abs(g.buf.astype(np.float64)) > EXACT)[0])
            raise FMUCallError(self.name, f"fmi3Get{_FMI_TYPE[g.kind]}", None,
                               f"output {g.names[k]} = {int(g.buf[k])} is beyond 2^53: the bus (float64) holds "
                               f"it only rounded; {self.info.label}")
        if g.kind in ("real", "float32") and not np.isfinite(g.buf).all():
            self.nonfinite(g.buf, g.names)
        self.out_values[g.where] = g.buf

    def nonfinite(self, values: np.ndarray, names: tuple[str, ...]) -> None:
        """Raise `NonFiniteOutputError` for the first value that is not finite (``values``: the outputs
        ``names`` say, in order). The session checks the outputs it reads, so the world need not
        (`FMUModule` declares ``finite_outputs=False``)."""
        k = int(np.flatnonzero(~np.isfinite(values))[0])
        value = float(values[k])
        port = names[k].split("[", 1)[0]
        where = f" (element {names[k]})" if names[k] != port else ""
        raise NonFiniteOutputError(self.name, "step", None, f"output {port!r} is {'NaN' if np.isnan(value) else value}"
                                   f"{where}; outputs must be finite numbers ({self.info.label})", port=port)

    def read_outputs(self) -> None:
        reals = self.out_values[:self.n_out]
        self.api.get_values("real", self.stepper.out_vrs, reals)
        if not np.isfinite(reals).all():
            self.nonfinite(reals, _names([s for s in unclocked(self.info.outputs) if s.type == "real"]))
        self.read_typed_outputs()

    def write_inputs(self) -> None:
        self.api.set_values("real", self.stepper.in_vrs, np.ascontiguousarray(self.in_values[:self.n_in]))
        self.write_typed_inputs()

    def set_params(self, values: dict[str, Any]) -> None:
        """Set parameters by name (one call per type)."""
        api = self.api
        for kind in (*BUS_KINDS, "string", "binary"):
            vrs, vals = [], []
            for name, value in values.items():
                sig = self.params[name]
                if sig.type == kind:
                    vrs += sig.vrs
                    vals += [value] if kind in ("string", "binary") else list(np.ravel(np.asarray(value)))
            if not vrs:
                continue
            refs = np.array(vrs, dtype=np.uint32)
            if kind == "string":
                api.set_strings(refs, [str(v) for v in vals])
            elif kind == "binary":
                api.set_binaries(refs, [bytes(v) for v in vals])
            else:
                api.set_values(kind, refs, np.array(vals, dtype=api.DTYPES[kind]))

    # -- lifecycle -----------------------------------------------------------------------------------
    def initialize(self, t0: float, params: dict[str, Any], origin_ns: int | None = None) -> None:
        """Parameters, then initialization mode at ``t0`` (the world's time, in seconds: the FMU's is
        ``t0 + start_time``; ``origin_ns`` the same in nanoseconds) with the current inputs; the events
        at ``t0`` (clocks that tick there); outputs read."""
        api = self.api
        self.set_params(params)
        api.enter_init(t0 + self.start_time)
        self.write_inputs()
        api.exit_init()
        self.initialized = True
        if self.events is not None:
            self.events.start(round(t0 * 1e9) if origin_ns is None else origin_ns)
        self.read_outputs()

    def reinitialize(self, t0: float, params: dict[str, Any], origin_ns: int | None = None) -> None:
        """Reset and initialize again (a fixed parameter changed before the world ran)."""
        self.api.reset()
        self.initialized = False
        self.unusable = None
        self.end_asked = None
        self.initialize(t0, params, origin_ns)

    def step(self, t_ns: int, dt_ns: int, save: bool) -> FMUState | None:
        """One step from ``t_ns`` (the fast path is inlined in `FMUModule.step`; this is the general one)."""
        stepper = self.stepper
        if self.unusable is not None or self.api.dead:
            self.require_usable(CALLS[self.api.version][2])
        if self.end_asked is not None:
            raise FMUTerminatedError(self.name, CALLS[self.api.version][2], None, self.end_asked)
        if dt_ns != stepper.dt_ns:
            stepper.set_step(dt_ns)
        if self.info.scheduled:  # no steps: the partitions that tick at the step's end run
            return self._activate(t_ns + dt_ns, save)
        if self.in_typed:
            self.write_typed_inputs()
        pool = self.pool if save else None
        events = self.events
        if events is not None:  # the state is taken after the events at the step's end
            events.before_step()
            pool = None
        slot = pool.take() if pool is not None else -1
        rc = stepper.fn(stepper.arg, t_ns, pool.address(slot) if pool is not None else 0)
        if rc:
            self.failed(rc, slot, t_ns)
        if events is not None:
            try:
                needed, _, early, _ = _step_flags(stepper._flags)
                if early:
                    needed = self.step_on(t_ns, dt_ns)
                if self.out_typed:
                    self.read_typed_outputs()
                events.handle(t_ns + dt_ns, needed)
            except ModuleError as exc:
                self._failed_call(exc, 3)
                raise
            return self.pool.capture() if save and self.pool is not None else None
        if self.out_typed:
            try:
                self.read_typed_outputs()
            except ModuleError as exc:
                if slot >= 0 and pool is not None:
                    pool.free.append(slot)
                self._failed_call(exc, 3)
                raise
        return FMUState(pool, slot) if pool is not None else None

    def _activate(self, t_ns: int, save: bool) -> FMUState | None:
        """Scheduled execution's step: the unclocked inputs set, the partitions due at ``t_ns`` run
        (`events.Events.activate`), the state taken after them."""
        try:
            self.write_inputs()
            self.events.activate(t_ns)
        except ModuleError as exc:
            self._failed_call(exc, 3)
            raise
        return self.pool.capture() if save and self.pool is not None else None

    def require_usable(self, call: str) -> None:
        """Refuse a call on an instance that failed for good (see the module docstring)."""
        if self.unusable is None and self.api is not None and self.api.dead:
            self.unusable = (f"{self.info.label} reported a fatal error earlier; no call is allowed on it but freeing "
                             f"it. {_WHAT_NOW}")
        if self.unusable is not None:
            raise FMUUnusableError(self.name, call, None, self.unusable)

    def failed(self, rc: int, slot: int = -1, t_ns: int | None = None) -> None:
        """Handle a non-zero step result: log a warning, or give the slot back and raise."""
        api = self.api
        call, status = decode(api.version, rc)
        if status == 1:
            api.check(call, 1)
            return
        if status == ENDED:  # the step stands; the end is asked at the next one
            said = api.sink.take()
            at = f" in its step from t={t_ns / 1e9 + self.start_time:g} s" if t_ns is not None else ""
            self.end_asked = (f"{self.info.label} asked to end the simulation{at} (that step stands)"
                              + (" (" + " | ".join(said) + ")" if said else ""))
            return
        if slot >= 0 and self.pool is not None:
            self.pool.free.append(slot)
        at = f" in its step from t={t_ns / 1e9 + self.start_time:g} s" if t_ns is not None else ""
        try:
            if status == TERMINATE or (status == 2 and call == "fmi2DoStep" and api.terminated()):
                said = api.sink.take()
                raise FMUTerminatedError(self.name, call, None, f"{self.info.label} asked to end the simulation{at}"
                                         + (" (" + " | ".join(said) + ")" if said else ""))
            if status == NONFINITE:
                self.nonfinite(self.out_values[:self.n_out], _names([s for s in unclocked(self.info.outputs)
                                                                     if s.type == "real"]))
            if status == EARLY_RETURN:
                raise FMUCallError(self.name, call, None, f"{self.info.label} returned early from a step it was not "
                                   "allowed to cut short")
            api.check(call, status)
            raise FMUCallError(self.name, call, None, f"{self.info.label}: status {status}")  # pragma: no cover
        except ModuleError as exc:
            self._failed_call(exc, status)
            raise

    def _failed_call(self, exc: ModuleError, status: int) -> None:
        """After a failed call: an instance that cannot be restored (or is dead) is unusable from now
        on; the error says so."""
        if self.unusable is not None or (status < 2 and not isinstance(exc, FMUTerminatedError)):
            return
        dead = self.api.dead
        if self.pool is not None and not dead:
            return  # the world restores a state from before, which the FMI standard allows
        if dead:
            why = "it reported a fatal error"
            self.unusable = (f"{self.info.label} reported a fatal error earlier ({exc.call}: {exc.cause}); no call is "
                             f"allowed on it but freeing it. {_WHAT_NOW}")
        else:
            why = f"it cannot restore a state from before ({self.lost_state_reason()})"
            self.unusable = (f"{self.info.label} failed earlier ({exc.call}: {exc.cause}) and {why}: the FMI "
                             f"standard allows only to reset or free it. {_WHAT_NOW}")
        exc.cause = f"{exc.cause}; {why}, so it cannot be used any more"  # the world makes its error from this
        exc.args = (f"{exc.args[0]}; {why}, so it cannot be used any more",)

    def lost_state_reason(self) -> str:
        if not self.info.can_get_set:
            return "canGetAndSetFMUstate is false"
        return "its state is not kept here (no rollback)"

    def step_on(self, t_ns: int, dt_ns: int) -> bool:
        """After a step that returned early (FMI 3.0 early return; allowed to FMUs with event mode):
        handle the event where the FMU stopped (event mode there when it says ``eventHandlingNeeded``),
        then step on from that time to the step's end, as often as it returns early. Whether the last
        piece needs event handling at the end."""
        api, stepper, events = self.api, self.stepper, self.events
        end = stepper.t0 + (t_ns + dt_ns) / 1e9
        since = stepper.t0 + t_ns / 1e9
        needed, _, _, reached = _step_flags(stepper._flags)
        flags = api._flag_bytes
        base = flags.ctypes.data
        for _ in range(MAX_EARLY_RETURNS):
            if not since <= reached < end:
                raise FMUCallError(self.name, "fmi3DoStep", None, f"{self.info.label} returned early at "
                                   f"t={reached:g} s, outside its step from t={since:g} s to t={end:g} s")
            if self.out_typed:
                self.read_typed_outputs()
            if needed:  # the event where it stopped
                events.handle(round((reached - stepper.t0) * 1e9), True)
            self.write_inputs()
            flags[:3] = 0
            api._call("do_step", api.instance, reached, end - reached, stepper.no_prior, base, base + 1, base + 2,
                      base + 24)
            needed, terminate, early, now = _step_flags(flags)
            if terminate:
                said = api.sink.take()
                raise FMUTerminatedError(self.name, "fmi3DoStep", None, f"{self.info.label} asked to end the "
                                         f"simulation in its step from t={reached:g} s"
                                         + (" (" + " | ".join(said) + ")" if said else ""))
            self.read_outputs()
            if not early:
                return needed
            since, reached = reached, now
        raise FMUCallError(self.name, "fmi3DoStep", None, f"{self.info.label} returned early {MAX_EARLY_RETURNS} "
                           f"times in one step from t={stepper.t0 + t_ns / 1e9:g} s")

    # -- states --------------------------------------------------------------------------------------
    def capture(self) -> FMUState:
        if self.pool is None:
            raise FMUError(f"{self.info.label}: this FMU cannot save its state (canGetAndSetFMUstate is false)")
        return self.pool.capture()

    def restore(self, state: FMUState | SerializedFMUState) -> FMUState:
        """Make ``state`` current; returns it as a state of this session's pool."""
        pool = self.pool
        if pool is None:
            raise FMUError(f"{self.info.label}: this FMU cannot restore a state (canGetAndSetFMUstate is false)")
        if isinstance(state, FMUState) and state.pool is not pool:
            state = state.pool.serialize(state.slot)
        if isinstance(state, SerializedFMUState):
            state = pool.load(state)
        if not isinstance(state, FMUState):
            raise FMUError(f"{self.info.label}: {state!r} is not an FMU state")
        pool.restore(state)
        self.unusable = None  # restored to a state from before the failure (FMI: allowed after an error)
        self.end_asked = None
        return state

    def serialize_handle(self, handle: int) -> SerializedFMUState:
        """The FMU state ``handle`` (of this instance) as bytes."""
        if not self.info.can_serialize:
            raise FMUError(f"{self.info.label}: this FMU cannot serialize its state (canSerializeFMUstate is false)")
        return SerializedFMUState(self.info.token, self.api.serialize(handle))

    def serialize(self, state: FMUState) -> SerializedFMUState:
        if not self.info.can_serialize:
            raise FMUError(f"{self.info.label}: this FMU cannot serialize its state (canSerializeFMUstate is false)")
        return state.pool.serialize(state.slot)

    def close(self) -> None:
        """Terminate (unless the instance failed for good), free every state and the instance, unload,
        delete the extracted files. Safe to call more than once and after any failure."""
        api, self.api = self.api, None
        try:
            if api is not None:
                if self.initialized and api.instance is not None and not api.dead and self.unusable is None:
                    with contextlib.suppress(Exception):
                        api.terminate()
                if getattr(self, "pool", None) is not None:
                    self.pool.close()
                api.free()
        finally:
            self._remove_dir()


def _extract(info: FmuInfo, folder: str) -> None:
    """Unzip the FMU within `archive`'s limits (size, ratio, no member outside ``folder``)."""
    from .archive import extract

    extract(info.path, folder, info.label)
