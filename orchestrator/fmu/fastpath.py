"""The step hot path: inputs in, DoStep, outputs out, state saved, with the fewest crossings into C.

With a C compiler (the one that builds FMUs), a small helper (``csrc/dyn_step.c``, compiled once
into the cache) makes the four FMI calls of a step from one ctypes call, reading and writing the
world's bus in place. Without one, `Stepper` makes the same calls from Python (about twice the
cost). Both take ``(plan, t_ns, slot)``, step from ``t_ns`` (plus the FMU's start time) by the bound
step size, check that the real outputs are finite (`NONFINITE` otherwise), and return 0
or a code `decode` turns into the failing call and its status. ``DYNABRAIN_FMU_FASTPATH=0``
forces the Python path.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import tempfile
from collections.abc import Callable
from ctypes import c_double, c_int, c_size_t, c_void_p
from pathlib import Path
from typing import Any

import numpy as np

from .api import FmuApi
from .build import compile_library, compiler, compiler_identity
from .errors import FMUBuildError
from .paths import SHARED_LIB_EXT, cache_dir, glue_dir

_log = logging.getLogger("dynabrain.fmu")
CALLS = {1: {1: "fmiSetReal", 2: "fmiDoStep", 3: "fmiGetReal", 4: "fmiGetFMUstate"},
         2: {1: "fmi2SetReal", 2: "fmi2DoStep", 3: "fmi2GetReal", 4: "fmi2GetFMUstate"},
         3: {1: "fmi3SetFloat64", 2: "fmi3DoStep", 3: "fmi3GetFloat64", 4: "fmi3GetFMUState"}}
TERMINATE, EARLY_RETURN, NONFINITE, ENDED = 6, 7, 8, 9
"""Step codes beyond the FMI statuses; ENDED: the step is done (outputs, state) and asked to end."""


class Plan(ctypes.Structure):
    """Mirror of ``Plan`` in dyn_step.c: what one step reads and writes."""

    _fields_ = [("instance", c_void_p), ("set_real", c_void_p), ("do_step", c_void_p), ("get_real", c_void_p),
                ("get_state", c_void_p), ("in_vr", c_void_p), ("n_in_vr", c_size_t), ("in_", c_void_p),
                ("n_in", c_size_t), ("out_vr", c_void_p), ("n_out_vr", c_size_t), ("out", c_void_p),
                ("n_out", c_size_t), ("fmi3", c_int), ("no_prior", c_int), ("h", c_double), ("t0", c_double),
                ("trace", c_void_p)]


@functools.cache
def helper() -> Callable[..., int] | None:
    """The compiled step helper, or None (no compiler, or ``DYNABRAIN_FMU_FASTPATH=0``)."""
    return _function("dyn_step")


@functools.cache
def group_helper() -> Callable[..., int] | None:
    """The helper that steps several FMUs in one call (``dyn_group``: `orchestrator.fmu.fused`), or None."""
    return _function("dyn_group")


def _function(name: str) -> Callable[..., int] | None:
    """A function of the helper library taking three pointers and returning an int, or None."""
    lib = _library()
    if lib is None:
        return None
    fn = getattr(lib, name)
    fn.argtypes = [c_void_p, c_void_p, c_void_p]
    fn.restype = c_int
    return fn


@functools.cache
def _library() -> ctypes.CDLL | None:
    if os.environ.get("DYNABRAIN_FMU_FASTPATH", "1") == "0":
        return None
    src = glue_dir() / "dyn_step.c"
    try:
        ident = compiler_identity(tuple(compiler()))
        digest = hashlib.sha256(src.read_bytes() + ident.encode()).hexdigest()[:16]
        lib = cache_dir() / "lib" / f"dyn_step-{digest}{SHARED_LIB_EXT}"
        if not lib.is_file():
            lib.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(suffix=SHARED_LIB_EXT, dir=lib.parent)
            os.close(fd)
            try:
                compile_library([src], Path(tmp), what="the FMU step helper")
                os.replace(tmp, lib)
            finally:
                if os.path.exists(tmp):
                    os.unlink(tmp)
        return ctypes.CDLL(str(lib))
    except (FMUBuildError, OSError) as exc:
        _log.info("FMU step helper unavailable, stepping FMUs from Python: %s", exc)
        return None


def decode(version: int, rc: int) -> tuple[str, int]:
    """(FMI function, status) of a step result code."""
    return CALLS[version][rc >> 4], rc & 15


class Stepper:
    """The reals of one FMU's step: value references bound once, buffers by `bind`, the step size
    by `set_step`. ``fn(arg, t_ns, slot)`` steps from ``t_ns``; ``slot`` is the address of a state
    slot to save the state into (0: none)."""

    def __init__(self, api: FmuApi, in_vrs: np.ndarray, n_in: int, out_vrs: np.ndarray, n_out: int, no_prior: bool):
        self.api = api
        self.version = api.version
        self.in_vrs, self.out_vrs = in_vrs, out_vrs
        self.n_in, self.n_out = n_in, n_out
        self.no_prior = no_prior
        self.trace: Callable[[str], None] | None = None
        self.c_helper = helper()
        self._keep: tuple[Any, ...] = ()
        self.plan = Plan()
        self.set_step(1_000_000)
        self.set_start_time(0.0)
        self._flags = np.zeros(4, dtype=np.float64).view(np.uint8)  # FMI 3 DoStep's flags and time
        self.fn: Callable[..., int]
        self.arg: int
        if self.c_helper is not None and api.on_call is None:
            self.fn, self.arg = self.c_helper, ctypes.addressof(self.plan)
        else:  # (calls traced: each is told before it is made)
            self.trace, self.fn, self.arg = api.on_call, self._py_step, 0

    @property
    def event_needed(self) -> int:
        """FMI 3.0: whether the last step (on the Python path) said eventHandlingNeeded."""
        return int(self._flags[0])

    @property
    def fast(self) -> bool:
        return self.fn is self.c_helper

    def use_python(self, trace: Callable[[str], None] | None = None) -> None:
        """Step from Python (isolation does, telling ``trace`` each FMI call before it is made)."""
        self.trace = trace
        self.fn, self.arg = self._py_step, 0

    def trace_to(self, address: int, trace: Callable[[str], None]) -> None:
        """Say the call under way (isolation records it for crash reports): the C helper writes its
        number (`CALLS`) as an int32 at ``address`` (0 between steps); the Python path tells ``trace``."""
        if self.fast:
            self.plan.trace = address
        else:
            self.use_python(trace)

    def bind(self, in_values: np.ndarray, out_values: np.ndarray) -> None:
        """Read inputs from ``in_values`` and write outputs to ``out_values`` (float64, contiguous)."""
        api, p = self.api, self.plan
        c = api.c
        p.instance = api.instance
        p.set_real, p.do_step = _addr(c["set_real"]), _addr(c["do_step"])
        p.get_real, p.get_state = _addr(c["get_real"]), _addr(c.get("get_state"))  # (FMI 1.0 has no states)
        p.in_vr, p.n_in_vr = self.in_vrs.ctypes.data, len(self.in_vrs)
        p.in_, p.n_in = in_values.ctypes.data, self.n_in
        p.out_vr, p.n_out_vr = self.out_vrs.ctypes.data, len(self.out_vrs)
        p.out, p.n_out = out_values.ctypes.data, self.n_out
        p.fmi3, p.no_prior = int(self.version == 3), int(self.no_prior)
        self._keep = (in_values, out_values)  # the plan holds their addresses
        # the real outputs, summed to check them (as plain doubles: a view of the bus made by ctypes says "<d")
        self._outs = memoryview(out_values[:self.n_out]).cast("B").cast("d")

    def set_step(self, dt_ns: int) -> None:
        self.dt_ns = dt_ns
        self.plan.h = dt_ns / 1e9

    def set_start_time(self, t0: float) -> None:
        """The FMU's time at world time 0: a step from ``t_ns`` starts at ``t0 + t_ns / 1e9`` seconds."""
        self.t0 = self.plan.t0 = float(t0)

    def _py_step(self, _arg: int, t_ns: int, slot: int) -> int:
        p, trace, names = self.plan, self.trace, CALLS[self.version]
        t, h = self.t0 + t_ns / 1e9, p.h
        warn = 0
        for call in (1, 2, 3, 4):
            if (call == 1 and not p.n_in_vr) or (call == 3 and not p.n_out_vr) or (call == 4 and not slot):
                continue
            if trace is not None:
                trace(names[call])
            status = self._one(call, t, h, slot)
            if status > 1:
                return (call << 4) | status
            if status == 1 and not warn:
                warn = (call << 4) | 1
            if call == 2 and self.version == 3 and self._flags[1]:
                warn = (2 << 4) | ENDED  # kept: outputs and state are taken, then the end is asked
        total = sum(self._outs)  # a sum is NaN or infinite when a value is (or when it overflows: then look)
        if not -1e309 < total < 1e309 and not np.isfinite(self._keep[1][:p.n_out]).all():
            return (3 << 4) | NONFINITE
        return warn

    def _one(self, call: int, t: float, h: float, slot: int) -> int:
        p, c, v3 = self.plan, self.api.c, self.version == 3
        if call == 1:
            return c["set_real"](p.instance, p.in_vr, p.n_in_vr, p.in_, *((p.n_in,) if v3 else ()))
        if call == 3:
            return c["get_real"](p.instance, p.out_vr, p.n_out_vr, p.out, *((p.n_out,) if v3 else ()))
        if call == 4:
            return c["get_state"](p.instance, slot)
        if v3:
            flags = self._flags
            flags[:3] = 0
            base = flags.ctypes.data
            return c["do_step"](p.instance, t, h, bool(p.no_prior), base, base + 1, base + 2, base + 24)
        return c["do_step"](p.instance, t, h, p.no_prior)


def _addr(fn: Any) -> int:
    return ctypes.cast(fn, c_void_p).value or 0
