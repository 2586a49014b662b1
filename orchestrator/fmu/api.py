"""The thin layer over an FMU binary: one Python method per FMI call, every status through one
checkpoint (`FmuApi.check`), which raises `FMUCallError` naming the FMU, the call, the status and
the FMU's own log lines. FMPy finds and loads the library; the calls go through prototypes of our
own that take plain addresses, so callers pass numpy buffers without per-call conversions.

`Fmi2Api` and `Fmi3Api` have the same methods; nothing above this file branches on the version.
"""

from __future__ import annotations

import ctypes
import itertools
import logging
import os
import pathlib
from collections import deque
from collections.abc import Callable
from ctypes import CFUNCTYPE, c_bool, c_char_p, c_double, c_int, c_size_t, c_void_p
from typing import Any, ClassVar

import numpy as np

from .errors import FMUCallError, FMUDiscardError, FMUError, status_name
from .info import FmuInfo

_log = logging.getLogger("dynabrain.fmu")
_P = c_void_p
_STATUS = ("OK", "WARNING", "DISCARD", "ERROR", "FATAL", "PENDING")

# -- the FMU's log messages, routed to the instance that logged them ------------------------------------
_SINKS: dict[int, LogSink] = {}
_KEYS = itertools.count(1)


_CALL_TRACE: list[Callable[[str], None]] = []


def trace_calls(fn: Callable[[str], None]) -> None:
    """Tell ``fn`` the name of every FMI call that instances made from now on in this process make,
    before it is made (their steps then go through Python). The child process of `checkproc` does,
    so that when an FMU kills it the parent can say which call did."""
    _CALL_TRACE[:] = [fn]


class LogSink:
    """The last messages an FMU instance logged (they go into error messages) and a logger."""

    def __init__(self, label: str):
        self.key = next(_KEYS)
        self.label = label
        self.messages: deque[str] = deque(maxlen=8)
        _SINKS[self.key] = self

    def add(self, status: int, category: str, message: str) -> None:
        text = f"[{_STATUS[status] if 0 <= status < len(_STATUS) else status}] {message}"
        self.messages.append(text)
        _log.log(logging.WARNING if status >= 1 else logging.DEBUG, "%s: %s", self.label, text)

    def take(self) -> list[str]:
        out = list(self.messages)
        self.messages.clear()
        return out

    def close(self) -> None:
        _SINKS.pop(self.key, None)


def _route(env: Any, status: int, category: bytes | None, message: bytes | None) -> None:
    sink = _SINKS.get(env or 0)
    text = (message or b"").decode("utf-8", "replace")
    if sink is None:
        _log.info("FMU log: %s", text)
    else:
        sink.add(status, (category or b"").decode("utf-8", "replace"), text)


def _route2(env: Any, name: bytes, status: int, category: bytes, message: bytes) -> None:
    _route(env, status, category, message)


def _fmi2_callbacks(key: int) -> Any:
    from fmpy import calloc, free
    from fmpy.fmi2 import fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFreeMemoryTYPE, fmi2CallbackFunctions
    from fmpy.logging import addLoggerProxy

    cb = fmi2CallbackFunctions()
    cb.logger = _LOGGER2
    cb.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
    cb.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
    cb.componentEnvironment = key
    addLoggerProxy(ctypes.byref(cb))  # formats the variadic message in C, then calls _route2
    return cb


def _make_loggers() -> tuple[Any, Any]:
    from fmpy.fmi2 import fmi2CallbackLoggerTYPE

    log3 = CFUNCTYPE(None, c_void_p, c_int, c_char_p, c_char_p)
    return fmi2CallbackLoggerTYPE(_route2), log3(_route)


_LOGGER2, _LOGGER3 = _make_loggers()
_CLOCK_UPDATE = CFUNCTYPE(None, c_void_p)(lambda env: None)  # (the output clocks are read after each partition)
_NO_LOCK = CFUNCTYPE(None)(lambda: None)


# -- the API ------------------------------------------------------------------------------------------------
def _bind(fn: Any, restype: Any, *argtypes: Any) -> Any:
    return CFUNCTYPE(restype, *argtypes)(ctypes.cast(fn, c_void_p).value)


class FmuApi:
    """One FMU instance's C API. ``instance`` is the component pointer (an int) once instantiated."""

    version: ClassVar[int]
    CALLS: ClassVar[dict[str, tuple[str, Any, tuple[Any, ...]]]]
    """method name -> (C function, result type, argument types)."""
    DTYPES: ClassVar[dict[str, Any]]

    def __init__(self, info: FmuInfo, unzip_dir: str, name: str):
        self.info, self.name, self.unzip_dir = info, name, unzip_dir
        self.sink = LogSink(f"{name} ({info.source or pathlib.Path(info.path).name})")
        self.on_call: Callable[[str], None] | None = _CALL_TRACE[0] if _CALL_TRACE else None
        """Told the FMI function about to be called (isolation and `trace_calls` record it for crash reports)."""
        self.instance: int | None = None
        self.dead = False
        self._size = c_size_t()
        self._fmu = self._load()
        self.c: dict[str, Any] = {}
        for key, (cname, restype, argtypes) in self.CALLS.items():
            self.c[key] = _bind(self._fmu._functions[self.symbol(cname)], restype, *argtypes)

    @staticmethod
    def symbol(cname: str) -> str:
        """The key FMPy loaded the FMI function ``cname`` under."""
        return cname

    def _load(self) -> Any:
        from fmpy.fmi1 import FMU1Slave
        from fmpy.fmi2 import FMU2Slave
        from fmpy.fmi3 import FMU3Slave

        cls = {1: FMU1Slave, 2: FMU2Slave, 3: FMU3Slave}[self.version]
        cwd = os.getcwd()  # FMPy changes the working folder while loading and not back when it fails
        try:
            return cls(guid=self.info.token, modelIdentifier=self.info.model_identifier,
                       unzipDirectory=self.unzip_dir, instanceName=self.name)
        except AttributeError as exc:
            symbol = str(exc).rsplit(":", 1)[-1].strip() or str(exc)
            raise FMUError(f"{self.info.label}: the binary lacks the FMI function {symbol} ({exc})") from None
        except Exception as exc:
            raise FMUError(f"{self.info.label}: cannot load the binary: {exc}") from None
        finally:
            os.chdir(cwd)

    # -- the checkpoint ---------------------------------------------------------------------------------
    def check(self, call: str, status: int) -> int:
        """Pass OK and Warning (logged) through; raise for anything else. A fatal status marks the
        instance dead: the FMI standard allows no further call on it."""
        if status == 0:
            return 0
        if status == 1:
            _log.warning("%s: %s returned %s %s", self.name, call, status_name(self.version, 1),
                         " | ".join(self.sink.take()))
            return 1
        if status >= 4:
            self.dead = True
        lines = self.sink.take()
        detail = f"{status_name(self.version, status)} from {self.info.label}"
        if lines:
            detail += "; the FMU said: " + " | ".join(lines)
        if status == 2:
            raise FMUDiscardError(self.name, call, None, detail)
        raise FMUCallError(self.name, call, None, detail)

    def enter(self, call: str) -> None:
        """Before each call: tell ``on_call``; refuse any call after a fatal status."""
        if self.on_call is not None:
            self.on_call(call)
        if self.dead:
            raise FMUCallError(self.name, call, None, f"{self.info.label} reported a fatal error earlier; no "
                               "call is allowed on it any more (with isolate: true it is restarted)")

    def _call(self, key: str, *args: Any) -> int:
        cname = self.CALLS[key][0]
        self.enter(cname)
        return self.check(cname, self.c[key](*args))

    # -- lifecycle --------------------------------------------------------------------------------------
    def instantiate(self, logging_on: bool = False) -> None:
        raise NotImplementedError

    def enter_init(self, t0: float) -> None:
        raise NotImplementedError

    def exit_init(self) -> None:
        self._call("exit_init", self.instance)

    def terminate(self) -> None:
        self._call("terminate", self.instance)

    def reset(self) -> None:
        self._call("reset", self.instance)

    def free(self) -> None:
        """Free the instance and unload the library (no call after a fatal status but the unload)."""
        try:
            if self.instance is not None and not self.dead:
                self.c["free_instance"](self.instance)
        finally:
            self.instance = None
            self.sink.close()
            try:
                self._fmu.freeLibrary()
            except Exception as exc:  # pragma: no cover - dlclose failing is not worth more than a log line
                _log.debug("%s: unloading the library failed: %s", self.name, exc)

    # -- values -----------------------------------------------------------------------------------------
    def set_values(self, kind: str, vrs: np.ndarray, values: np.ndarray) -> None:
        """Set variables of a number or boolean ``kind`` (`info.BUS_KINDS`) from ``values`` (``DTYPES[kind]``)."""
        raise NotImplementedError

    def get_values(self, kind: str, vrs: np.ndarray, out: np.ndarray) -> None:
        raise NotImplementedError

    def set_strings(self, vrs: np.ndarray, values: list[str]) -> None:
        buf = (c_char_p * len(values))(*[v.encode("utf-8") for v in values])
        self._call("set_string", self.instance, vrs.ctypes.data, len(vrs), ctypes.addressof(buf),
                   *self._count(len(values)))

    def get_strings(self, vrs: np.ndarray) -> list[str]:
        buf = (c_char_p * len(vrs))()
        self._call("get_string", self.instance, vrs.ctypes.data, len(vrs), ctypes.addressof(buf),
                   *self._count(len(vrs)))
        return [(v or b"").decode("utf-8", "replace") for v in buf]

    def set_binaries(self, vrs: np.ndarray, values: list[bytes]) -> None:
        raise FMUError(f"{self.info.label}: FMI {self.version}.0 has no binary variables")

    def get_binaries(self, vrs: np.ndarray) -> list[bytes]:
        raise FMUError(f"{self.info.label}: FMI {self.version}.0 has no binary variables")

    def _count(self, n: int) -> tuple[int, ...]:
        """The value count FMI 3.0 calls take after the values (FMI 2.0 takes none)."""
        return (n,) if self.version == 3 else ()

    def terminated(self) -> bool:
        """Whether the FMU asked to end the simulation in its last step (FMI 2.0 asks with fmi2Discard
        and says so through fmi2GetBooleanStatus(fmi2Terminated); FMI 3.0 says it in fmi3DoStep)."""
        return False

    def do_step(self, t: float, h: float, no_prior: bool) -> int:
        raise NotImplementedError

    # -- FMU states -------------------------------------------------------------------------------------
    def get_state(self, slot: int) -> None:
        """Save the state into ``*slot`` (a new handle when it holds NULL, else overwritten in place)."""
        self._call("get_state", self.instance, slot)

    def set_state(self, handle: int) -> None:
        self._call("set_state", self.instance, handle)

    def free_state(self, slot: int) -> None:
        self._call("free_state", self.instance, slot)

    def serialize(self, handle: int) -> bytes:
        size = c_size_t()
        self._call("state_size", self.instance, handle, ctypes.addressof(size))
        buf = ctypes.create_string_buffer(size.value)
        self._call("serialize", self.instance, handle, ctypes.addressof(buf), size.value)
        return buf.raw

    def serialize_into(self, handle: int, address: int, capacity: int) -> int:
        """Serialize the state ``handle`` into ``capacity`` bytes at ``address`` when it fits; its size
        either way (isolation writes it straight into the step's shared memory)."""
        size = self._size
        self._call("state_size", self.instance, handle, ctypes.addressof(size))
        if size.value <= capacity:
            self._call("serialize", self.instance, handle, address, size.value)
        return size.value

    def deserialize(self, data: bytes, slot: int) -> None:
        buf = ctypes.create_string_buffer(data, len(data))
        self._call("deserialize", self.instance, ctypes.addressof(buf), len(data), slot)


_COMMON2 = {
    "instantiate": ("fmi2Instantiate", c_void_p, (c_char_p, c_int, c_char_p, c_char_p, _P, c_int, c_int)),
    "free_instance": ("fmi2FreeInstance", None, (_P,)),
    "setup": ("fmi2SetupExperiment", c_int, (_P, c_int, c_double, c_double, c_int, c_double)),
    "enter_init": ("fmi2EnterInitializationMode", c_int, (_P,)),
    "exit_init": ("fmi2ExitInitializationMode", c_int, (_P,)),
    "terminate": ("fmi2Terminate", c_int, (_P,)),
    "reset": ("fmi2Reset", c_int, (_P,)),
    "do_step": ("fmi2DoStep", c_int, (_P, c_double, c_double, c_int)),
    "get_state": ("fmi2GetFMUstate", c_int, (_P, _P)),
    "set_state": ("fmi2SetFMUstate", c_int, (_P, _P)),
    "free_state": ("fmi2FreeFMUstate", c_int, (_P, _P)),
    "state_size": ("fmi2SerializedFMUstateSize", c_int, (_P, _P, _P)),
    "serialize": ("fmi2SerializeFMUstate", c_int, (_P, _P, _P, c_size_t)),
    "deserialize": ("fmi2DeSerializeFMUstate", c_int, (_P, _P, c_size_t, _P)),
    "boolean_status": ("fmi2GetBooleanStatus", c_int, (_P, c_int, _P)),
}
_FMI2_TERMINATED = 3  # fmi2StatusKind fmi2Terminated
_TYPES2 = {"real": "Real", "integer": "Integer", "boolean": "Boolean", "string": "String"}


class Fmi2Api(FmuApi):
    version = 2
    CALLS: ClassVar[dict[str, tuple[str, Any, tuple[Any, ...]]]] = {
        **_COMMON2,
        **{f"{op}_{k}": (f"fmi2{op.capitalize()}{t}", c_int, (_P, _P, c_size_t, _P))
           for op in ("set", "get") for k, t in _TYPES2.items()},
    }
    DTYPES: ClassVar[dict[str, Any]] = {"real": np.float64, "integer": np.int32, "boolean": np.int32}

    def terminated(self) -> bool:
        value = ctypes.c_int(0)
        self.enter("fmi2GetBooleanStatus")
        status = self.c["boolean_status"](self.instance, _FMI2_TERMINATED, ctypes.addressof(value))
        if status > 1:  # an FMU that cannot say has not asked
            self.sink.take()
            return False
        return bool(value.value)

    def instantiate(self, logging_on: bool = False) -> None:
        self._callbacks = _fmi2_callbacks(self.sink.key)
        uri = pathlib.Path(self.unzip_dir, "resources").as_uri()
        self.enter("fmi2Instantiate")
        ptr = self.c["instantiate"](self.name.encode(), 1, self.info.token.encode(), uri.encode(),
                                    ctypes.addressof(self._callbacks), 0, int(logging_on))
        if not ptr:
            lines = self.sink.take()
            raise FMUCallError(self.name, "fmi2Instantiate", None, f"{self.info.label} returned no instance"
                               + ("; the FMU said: " + " | ".join(lines) if lines else ""))
        self.instance = ptr

    def enter_init(self, t0: float) -> None:
        self._call("setup", self.instance, 0, 0.0, t0, 0, 0.0)
        self._call("enter_init", self.instance)

    def set_values(self, kind: str, vrs: np.ndarray, values: np.ndarray) -> None:
        if len(vrs):
            self._call(f"set_{kind}", self.instance, vrs.ctypes.data, len(vrs), values.ctypes.data)

    def get_values(self, kind: str, vrs: np.ndarray, out: np.ndarray) -> None:
        if len(vrs):
            self._call(f"get_{kind}", self.instance, vrs.ctypes.data, len(vrs), out.ctypes.data)

    def do_step(self, t: float, h: float, no_prior: bool) -> int:
        return self._call("do_step", self.instance, t, h, int(no_prior))


_TYPES3 = {"real": "Float64", "float32": "Float32", "int8": "Int8", "uint8": "UInt8", "int16": "Int16",
           "uint16": "UInt16", "integer": "Int32", "uint32": "UInt32", "int64": "Int64", "uint64": "UInt64",
           "boolean": "Boolean", "string": "String"}


class Fmi3Api(FmuApi):
    version = 3
    CALLS: ClassVar[dict[str, tuple[str, Any, tuple[Any, ...]]]] = {
        **{k: (c.replace("fmi2", "fmi3").replace("FMUstate", "FMUState"), r, a) for k, (c, r, a) in _COMMON2.items()
           if k not in ("instantiate", "setup", "enter_init", "do_step", "deserialize", "boolean_status")},
        "instantiate": ("fmi3InstantiateCoSimulation", c_void_p,
                        (c_char_p, c_char_p, c_char_p, c_bool, c_bool, c_bool, c_bool, _P, c_size_t, _P, _P, _P)),
        "enter_init": ("fmi3EnterInitializationMode", c_int, (_P, c_bool, c_double, c_double, c_bool, c_double)),
        "do_step": ("fmi3DoStep", c_int, (_P, c_double, c_double, c_bool, _P, _P, _P, _P)),
        "deserialize": ("fmi3DeserializeFMUState", c_int, (_P, _P, c_size_t, _P)),
        **{f"{op}_{k}": (f"fmi3{op.capitalize()}{t}", c_int, (_P, _P, c_size_t, _P, c_size_t))
           for op in ("set", "get") for k, t in _TYPES3.items()},
        "set_binary": ("fmi3SetBinary", c_int, (_P, _P, c_size_t, _P, _P, c_size_t)),
        "get_binary": ("fmi3GetBinary", c_int, (_P, _P, c_size_t, _P, _P, c_size_t)),
        "enter_event_mode": ("fmi3EnterEventMode", c_int, (_P,)),
        "enter_step_mode": ("fmi3EnterStepMode", c_int, (_P,)),
        "update_discrete_states": ("fmi3UpdateDiscreteStates", c_int, (_P, _P, _P, _P, _P, _P, _P)),
        "set_clock": ("fmi3SetClock", c_int, (_P, _P, c_size_t, _P)),
        "get_clock": ("fmi3GetClock", c_int, (_P, _P, c_size_t, _P)),
        "get_interval": ("fmi3GetIntervalDecimal", c_int, (_P, _P, c_size_t, _P, _P)),
        "instantiate_se": ("fmi3InstantiateScheduledExecution", c_void_p,
                           (c_char_p, c_char_p, c_char_p, c_bool, c_bool, _P, _P, _P, _P, _P)),
        "activate": ("fmi3ActivateModelPartition", c_int, (_P, c_int, c_double)),
    }
    DTYPES: ClassVar[dict[str, Any]] = {"real": np.float64, "float32": np.float32, "int8": np.int8, "uint8": np.uint8,
                                        "int16": np.int16, "uint16": np.uint16, "integer": np.int32,
                                        "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
                                        "boolean": np.bool_}

    def __init__(self, info: FmuInfo, unzip_dir: str, name: str):
        super().__init__(info, unzip_dir, name)
        self.flags = np.zeros(4, dtype=np.float64)  # eventHandlingNeeded, terminate, earlyReturn; lastSuccessfulTime
        self._flag_bytes = self.flags.view(np.uint8)

    def instantiate(self, logging_on: bool = False) -> None:
        resources = os.path.join(self.unzip_dir, "resources") + os.sep
        if self.info.scheduled:
            return self._instantiate_scheduled(resources, logging_on)
        self.enter("fmi3InstantiateCoSimulation")
        event_mode = bool(self.info.clocks)  # with event mode the session also handles an early return
        ptr = self.c["instantiate"](self.name.encode(), self.info.token.encode(), resources.encode(), False,
                                    logging_on, event_mode, event_mode, None, 0, self.sink.key,
                                    ctypes.cast(_LOGGER3, c_void_p).value, None)
        if not ptr:
            lines = self.sink.take()
            raise FMUCallError(self.name, "fmi3InstantiateCoSimulation", None, f"{self.info.label} returned no "
                               "instance" + ("; the FMU said: " + " | ".join(lines) if lines else ""))
        self.instance = ptr

    def _instantiate_scheduled(self, resources: str, logging_on: bool) -> None:
        """Scheduled execution: the FMU says an output clock ticked with the clock update callback (it is
        then read with fmi3GetClock after the partition); nothing preempts here, so no locks."""
        self.enter("fmi3InstantiateScheduledExecution")
        ptr = self.c["instantiate_se"](self.name.encode(), self.info.token.encode(), resources.encode(), False,
                                       logging_on, self.sink.key, ctypes.cast(_LOGGER3, c_void_p).value,
                                       ctypes.cast(_CLOCK_UPDATE, c_void_p).value,
                                       ctypes.cast(_NO_LOCK, c_void_p).value, ctypes.cast(_NO_LOCK, c_void_p).value)
        if not ptr:
            lines = self.sink.take()
            raise FMUCallError(self.name, "fmi3InstantiateScheduledExecution", None, f"{self.info.label} returned "
                               "no instance" + ("; the FMU said: " + " | ".join(lines) if lines else ""))
        self.instance = ptr

    def activate(self, vr: int, t: float) -> None:
        """Scheduled execution: run the model partition of input clock ``vr`` at FMU time ``t``."""
        self._call("activate", self.instance, vr, t)

    def enter_init(self, t0: float) -> None:
        self._call("enter_init", self.instance, False, 0.0, t0, False, 0.0)

    def set_values(self, kind: str, vrs: np.ndarray, values: np.ndarray) -> None:
        if len(vrs):
            self._call(f"set_{kind}", self.instance, vrs.ctypes.data, len(vrs), values.ctypes.data, values.size)

    def get_values(self, kind: str, vrs: np.ndarray, out: np.ndarray) -> None:
        if len(vrs):
            self._call(f"get_{kind}", self.instance, vrs.ctypes.data, len(vrs), out.ctypes.data, out.size)

    def set_binaries(self, vrs: np.ndarray, values: list[bytes]) -> None:
        n = len(values)
        data = [ctypes.create_string_buffer(v, len(v) or 1) for v in values]
        sizes = (c_size_t * n)(*[len(v) for v in values])
        ptrs = (c_void_p * n)(*[ctypes.addressof(d) for d in data])
        self._call("set_binary", self.instance, vrs.ctypes.data, len(vrs), ctypes.addressof(sizes),
                   ctypes.addressof(ptrs), n)

    def get_binaries(self, vrs: np.ndarray) -> list[bytes]:
        n = len(vrs)
        sizes, ptrs = (c_size_t * n)(), (c_void_p * n)()
        self._call("get_binary", self.instance, vrs.ctypes.data, n, ctypes.addressof(sizes), ctypes.addressof(ptrs), n)
        return [ctypes.string_at(p, size) if size else b"" for p, size in zip(ptrs, sizes, strict=True)]

    # -- event mode and clocks (see `clocks`) ------------------------------------------------------------
    def enter_event_mode(self) -> None:
        self._call("enter_event_mode", self.instance)

    def enter_step_mode(self) -> None:
        self._call("enter_step_mode", self.instance)

    def update_discrete_states(self) -> tuple[bool, bool]:
        """(discreteStatesNeedUpdate, terminateSimulation)."""
        flags = (ctypes.c_bool * 5)()
        time = ctypes.c_double()
        a = ctypes.addressof(flags)
        self._call("update_discrete_states", self.instance, a, a + 1, a + 2, a + 3, a + 4, ctypes.addressof(time))
        return bool(flags[0]), bool(flags[1])

    def set_clocks(self, vrs: np.ndarray, active: np.ndarray) -> None:
        if len(vrs):
            self._call("set_clock", self.instance, vrs.ctypes.data, len(vrs), active.ctypes.data)

    def get_clocks(self, vrs: np.ndarray) -> np.ndarray:
        out = np.zeros(len(vrs), dtype=np.bool_)
        if len(vrs):
            self._call("get_clock", self.instance, vrs.ctypes.data, len(vrs), out.ctypes.data)
        return out

    def get_intervals(self, vrs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(intervals in seconds, qualifiers: 0 not yet known, 1 unchanged, 2 changed)."""
        intervals, qualifiers = np.zeros(len(vrs)), np.zeros(len(vrs), dtype=np.int32)
        if len(vrs):
            self._call("get_interval", self.instance, vrs.ctypes.data, len(vrs), intervals.ctypes.data,
                       qualifiers.ctypes.data)
        return intervals, qualifiers

    def do_step(self, t: float, h: float, no_prior: bool) -> int:
        base = self._flag_bytes.ctypes.data
        status = self._call("do_step", self.instance, t, h, no_prior, base, base + 1, base + 2, base + 24)
        if self._flag_bytes[1]:
            raise FMUCallError(self.name, "fmi3DoStep", None, f"{self.info.label} asked to end the simulation "
                               f"(terminateSimulation) at t={t + h:g} s")
        return status


def make_api(info: FmuInfo, unzip_dir: str, name: str) -> FmuApi:
    if info.version == 1:
        from .api1 import Fmi1Api

        return Fmi1Api(info, unzip_dir, name)
    return (Fmi2Api if info.version == 2 else Fmi3Api)(info, unzip_dir, name)
