"""FMI 1.0 co-simulation under `api`'s methods, so nothing above it branches on the version.

FMI 1.0 differs where the adapter meets it: the functions are named after the model
(``<modelIdentifier>_fmiDoStep``; FMPy finds them), initialization is one call
(``fmiInitializeSlave``, made at `exit_init`, after the parameters and inputs are set), a boolean is
one byte, the callbacks are passed by value and the logger is told the instance, not an environment
of ours. There are no FMU states: an FMI 1.0 FMU never rolls back, and every step is a new step.
"""

from __future__ import annotations

import ctypes
import pathlib
from ctypes import CFUNCTYPE, Structure, c_bool, c_char_p, c_double, c_int, c_size_t, c_void_p
from typing import Any, ClassVar

import numpy as np

from .api import FmuApi, LogSink, _log
from .errors import FMUCallError

_P = c_void_p
_BY_INSTANCE: dict[int, LogSink] = {}
"""The sink of each instance (FMI 1.0's logger is told the instance)."""
_INSTANTIATING: list[LogSink] = []
"""The sink of the instance being made (its messages come before its address is known)."""


def _route1(component: Any, name: bytes | None, status: int, category: bytes | None, message: bytes | None) -> None:
    sink = _BY_INSTANCE.get(component or 0) or (_INSTANTIATING[-1] if _INSTANTIATING else None)
    text = (message or b"").decode("utf-8", "replace")
    if sink is None:
        _log.info("FMU log: %s", text)
    else:
        sink.add(status, (category or b"").decode("utf-8", "replace"), text)


_LOGGER1 = CFUNCTYPE(None, c_void_p, c_char_p, c_int, c_char_p, c_char_p)(_route1)  # (the format's arguments unread:
# a dynabrain FMU escapes '%'; another FMU's message is shown as its format)


class Callbacks1(Structure):
    """fmiCallbackFunctions (FMI 1.0 co-simulation), passed by value."""

    _fields_ = [("logger", c_void_p), ("allocateMemory", c_void_p), ("freeMemory", c_void_p),
                ("stepFinished", c_void_p)]


def _memory_functions() -> tuple[int, int]:
    from fmpy import calloc, free

    return ctypes.cast(calloc, c_void_p).value or 0, ctypes.cast(free, c_void_p).value or 0


class Fmi1Api(FmuApi):
    version = 1
    CALLS: ClassVar[dict[str, tuple[str, Any, tuple[Any, ...]]]] = {
        "instantiate": ("fmiInstantiateSlave", c_void_p, (c_char_p, c_char_p, c_char_p, c_char_p, c_double, c_bool,
                                                          c_bool, Callbacks1, c_bool)),
        "free_instance": ("fmiFreeSlaveInstance", None, (_P,)),
        "init_slave": ("fmiInitializeSlave", c_int, (_P, c_double, c_bool, c_double)),
        "terminate": ("fmiTerminateSlave", c_int, (_P,)),
        "reset": ("fmiResetSlave", c_int, (_P,)),
        "do_step": ("fmiDoStep", c_int, (_P, c_double, c_double, c_bool)),
        **{f"{op}_{k}": (f"fmi{op.capitalize()}{t}", c_int, (_P, _P, c_size_t, _P))
           for op in ("set", "get") for k, t in (("real", "Real"), ("integer", "Integer"), ("boolean", "Boolean"),
                                                 ("string", "String"))},
    }
    DTYPES: ClassVar[dict[str, Any]] = {"real": np.float64, "integer": np.int32, "boolean": np.int8}
    MIME_TYPE = b"application/x-fmu-sharedlibrary"

    @staticmethod
    def symbol(cname: str) -> str:
        return "fmi1" + cname[3:]  # FMPy's key: fmi1DoStep for <modelIdentifier>_fmiDoStep

    def instantiate(self, logging_on: bool = False) -> None:
        alloc, free = _memory_functions()
        self._callbacks = Callbacks1(ctypes.cast(_LOGGER1, c_void_p).value, alloc, free, None)
        location = pathlib.Path(self.unzip_dir).as_uri()
        self.enter("fmiInstantiateSlave")
        _INSTANTIATING.append(self.sink)
        try:
            ptr = self.c["instantiate"](self.name.encode(), self.info.token.encode(), location.encode(),
                                        self.MIME_TYPE, 0.0, False, False, self._callbacks, logging_on)
        finally:
            _INSTANTIATING.pop()
        if not ptr:
            lines = self.sink.take()
            raise FMUCallError(self.name, "fmiInstantiateSlave", None, f"{self.info.label} returned no instance"
                               + ("; the FMU said: " + " | ".join(lines) if lines else ""))
        self.instance = ptr
        _BY_INSTANCE[ptr] = self.sink

    def enter_init(self, t0: float) -> None:
        """FMI 1.0 has no initialization mode: parameters and inputs are set before `exit_init`."""
        self._t0 = t0

    def exit_init(self) -> None:
        self._call("init_slave", self.instance, self._t0, False, 0.0)

    def set_values(self, kind: str, vrs: np.ndarray, values: np.ndarray) -> None:
        if len(vrs):
            self._call(f"set_{kind}", self.instance, vrs.ctypes.data, len(vrs), values.ctypes.data)

    def get_values(self, kind: str, vrs: np.ndarray, out: np.ndarray) -> None:
        if len(vrs):
            self._call(f"get_{kind}", self.instance, vrs.ctypes.data, len(vrs), out.ctypes.data)

    def do_step(self, t: float, h: float, no_prior: bool) -> int:
        return self._call("do_step", self.instance, t, h, True)  # every step is a new one (no FMU states)

    def free(self) -> None:
        if self.instance is not None:
            _BY_INSTANCE.pop(self.instance, None)
        super().free()
