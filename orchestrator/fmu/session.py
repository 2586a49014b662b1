"""One FMU instance at run time: extracted, loaded, instantiated, initialized, stepped, freed.

`FMUModule` drives a session in the world's process; the isolation worker drives one in a child
process. A session exchanges values through two flat float64 arrays bound with `bind`: every input
and every output in port order (reals first, then integers, then booleans, as `info` orders them).
The reals go to and from the FMU in one call each; integers and booleans are converted around it.
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

from .api import FmuApi, make_api
from .errors import FMUCallError, FMUError
from .fastpath import CALLS, EARLY_RETURN, TERMINATE, Stepper, decode
from .info import FmuInfo, Signal
from .states import FMUState, SerializedFMUState, StatePool


@dataclass(frozen=True)
class _Typed:
    """Integer or boolean signals of one direction: their value references, their place in the
    flat array, and the FMU-typed buffer they go through."""

    kind: str
    vrs: np.ndarray
    start: int
    stop: int
    buf: np.ndarray


def _vrs(signals: list[Signal]) -> np.ndarray:
    return np.array([vr for s in signals for vr in s.vrs], dtype=np.uint32)


def _typed(api: FmuApi, signals: tuple[Signal, ...]) -> tuple[int, list[_Typed]]:
    """(number of real values, the integer and boolean groups after them)."""
    n_real = sum(s.size for s in signals if s.type == "real")
    groups, at = [], n_real
    for kind in ("integer", "boolean"):
        sigs = [s for s in signals if s.type == kind]
        n = sum(s.size for s in sigs)
        if n:
            groups.append(_Typed(kind, _vrs(sigs), at, at + n, np.zeros(n, dtype=api.DTYPES[kind])))
        at += n
    return n_real, groups


class Session:
    """A loaded and instantiated FMU. ``rollback``: keep states (a `StatePool`) for history;
    ``folder``: where to extract the FMU (default: a temporary folder removed at `close`)."""

    def __init__(self, info: FmuInfo, name: str, *, rollback: bool, folder: str | None = None):
        self.info, self.name = info, name
        if folder is not None:  # a folder its owner removes (isolation: even when this process dies)
            os.makedirs(folder, exist_ok=True)
        self.dir = folder or tempfile.mkdtemp(prefix="dynabrain-fmu-")
        self._remove_dir = weakref.finalize(self, shutil.rmtree, self.dir, True)  # also if never closed
        self.api: FmuApi | None = None
        self.initialized = False
        try:
            _extract(info, self.dir)
            self.api = make_api(info, self.dir, name)
            self.api.instantiate()
        except BaseException:
            self.close()
            raise
        api = self.api
        self.n_in, self.in_typed = _typed(api, info.inputs)
        self.n_out, self.out_typed = _typed(api, info.outputs)
        self.n_in_all = sum(s.size for s in info.inputs)
        self.n_out_all = sum(s.size for s in info.outputs)
        real_in = [s for s in info.inputs if s.type == "real"]
        real_out = [s for s in info.outputs if s.type == "real"]
        self.stepper = Stepper(api, _vrs(real_in), self.n_in, _vrs(real_out), self.n_out, no_prior=not rollback)
        self.pool = StatePool(api) if rollback and info.can_get_set else None
        self.params = {s.name: s for s in info.params}
        self.bind(np.zeros(self.n_in_all), np.zeros(self.n_out_all))

    # -- values --------------------------------------------------------------------------------------
    def bind(self, in_values: np.ndarray, out_values: np.ndarray) -> None:
        """Read inputs from ``in_values`` and write outputs to ``out_values`` (float64, contiguous,
        every input / output in port order)."""
        self.in_values, self.out_values = in_values, out_values
        self.stepper.bind(in_values, out_values)

    def write_typed_inputs(self) -> None:
        for g in self.in_typed:
            values = self.in_values[g.start:g.stop]
            g.buf[...] = values != 0 if g.kind == "boolean" else np.rint(values)
            self.api.set_values(g.kind, g.vrs, g.buf)

    def read_typed_outputs(self) -> None:
        for g in self.out_typed:
            self.api.get_values(g.kind, g.vrs, g.buf)
            self.out_values[g.start:g.stop] = g.buf

    def read_outputs(self) -> None:
        self.api.get_values("real", self.stepper.out_vrs, self.out_values[:self.n_out])
        self.read_typed_outputs()

    def write_inputs(self) -> None:
        self.api.set_values("real", self.stepper.in_vrs, np.ascontiguousarray(self.in_values[:self.n_in]))
        self.write_typed_inputs()

    def set_params(self, values: dict[str, Any]) -> None:
        """Set parameters by name (one call per type)."""
        api = self.api
        for kind in ("real", "integer", "boolean"):
            vrs, vals = [], []
            for name, value in values.items():
                sig = self.params[name]
                if sig.type == kind:
                    vrs += sig.vrs
                    vals += list(np.ravel(np.asarray(value)))
            if vrs:
                api.set_values(kind, np.array(vrs, dtype=np.uint32), np.array(vals, dtype=api.DTYPES[kind]))

    # -- lifecycle -----------------------------------------------------------------------------------
    def initialize(self, t0: float, params: dict[str, Any]) -> None:
        """Parameters, then initialization mode at ``t0`` with the current inputs; outputs read."""
        api = self.api
        self.set_params(params)
        api.enter_init(t0)
        self.write_inputs()
        api.exit_init()
        self.initialized = True
        self.read_outputs()

    def reinitialize(self, t0: float, params: dict[str, Any]) -> None:
        """Reset and initialize again (a fixed parameter changed before the world ran)."""
        self.api.reset()
        self.initialized = False
        self.initialize(t0, params)

    def step(self, t_ns: int, dt_ns: int, save: bool) -> FMUState | None:
        """One step from ``t_ns`` (the fast path is inlined in `FMUModule.step`; this is the general one)."""
        stepper = self.stepper
        if self.api.dead:
            self.api.enter(CALLS[self.api.version][2])  # raises: no call after a fatal status
        if dt_ns != stepper.dt_ns:
            stepper.set_step(dt_ns)
        if self.in_typed:
            self.write_typed_inputs()
        pool = self.pool if save else None
        slot = pool.take() if pool is not None else -1
        rc = stepper.fn(stepper.arg, t_ns, pool.address(slot) if pool is not None else 0)
        if rc:
            self.failed(rc, slot)
        if self.out_typed:
            self.read_typed_outputs()
        return FMUState(pool, slot) if pool is not None else None

    def failed(self, rc: int, slot: int = -1) -> None:
        """Handle a non-zero step result: log a warning, or give the slot back and raise."""
        call, status = decode(self.api.version, rc)
        if status == 1:
            self.api.check(call, 1)
            return
        if slot >= 0 and self.pool is not None:
            self.pool.free.append(slot)
        if status == TERMINATE:
            raise FMUCallError(self.name, call, None, f"{self.info.label} asked to end the simulation "
                               "(terminateSimulation)")
        if status == EARLY_RETURN:
            raise FMUCallError(self.name, call, None, f"{self.info.label} returned early from a step it was not "
                               "allowed to cut short")
        self.api.check(call, status)

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
        return state

    def serialize(self, state: FMUState) -> SerializedFMUState:
        if not self.info.can_serialize:
            raise FMUError(f"{self.info.label}: this FMU cannot serialize its state (canSerializeFMUstate is false)")
        return state.pool.serialize(state.slot)

    def close(self) -> None:
        """Terminate, free every state and the instance, unload, delete the extracted files. Safe to
        call more than once and after any failure."""
        api, self.api = self.api, None
        try:
            if api is not None:
                if self.initialized and api.instance is not None and not api.dead:
                    with contextlib.suppress(Exception):
                        api.terminate()
                if getattr(self, "pool", None) is not None:
                    self.pool.close()
                api.free()
        finally:
            self._remove_dir()


def _extract(info: FmuInfo, folder: str) -> None:
    from fmpy import extract

    try:
        extract(info.path, folder)
    except Exception as exc:
        raise FMUError(f"{info.label}: cannot extract: {exc}") from None
