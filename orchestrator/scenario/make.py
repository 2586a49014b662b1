"""Modules made from a spec, in this one place: a scenario's ``modules:`` entry, an ``add`` event, a
bridge client's ``add_module`` and a recorded ``module_added`` event that ``replay --verify`` makes
again all come here.

A spec is the scenario's module syntax, as a mapping (or any object with those attributes)::

    {name: servo, python: dynabrain.modules.servo:Servo, params: {kp: 100}, targets: [j1]}
    {name: floor, fmu: fmus/moving_floor, isolate: true, call_timeout: 2s, params: {amplitude: 0.05}}

``period`` and ``connect`` belong to `World.add_module`, not to the module, and are ignored here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from ..kernel.errors import DynabrainError
from ..kernel.extras import hint
from ..kernel.module import Module
from ..kernel.plugins import ClassNotAllowedError, ClassPolicy, resolve_module_class
from ..kernel.units import parse_duration_ns

SPEC_KEYS = ("name", "python", "fmu", "isolate", "call_timeout", "start_time", "params", "targets")
"""The keys `make_module` reads (a spec may hold ``period`` and ``connect`` too)."""


class ModuleSpecError(DynabrainError):
    """A module spec that makes no module; ``field`` names the spec's key at fault (``python``,
    ``fmu``, ``params``, ``isolate``, ``call_timeout``), or is None for the spec as a whole."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field


class ModuleNotAllowedError(ModuleSpecError):
    """A ``python:`` class path that `plugins.ClassPolicy` refuses (nothing was imported)."""

    def __init__(self, python: str, allowed: Sequence[str], message: str | None = None):
        super().__init__(message or f"module class {python!r} is not allowed", "python")
        self.python, self.allowed = python, tuple(allowed)


def make_module(spec: Mapping[str, Any] | Any, *, base_dir: str = ".", allow_python: Sequence[str] = (),
                local_modules: bool = True) -> Module:
    """The module ``spec`` describes, constructed (not yet added to a world).

    ``base_dir``: the folder an FMU path is relative to (the scenario's); a ``python:`` class in a
    module of that folder is allowed (the scenario's own) unless ``local_modules`` is false.
    ``allow_python``: the packages (or ``fnmatch`` patterns on the class path) the user allowed
    besides dynabrain's own and the registered classes (`plugins.ClassPolicy`); any other class is
    refused before it is imported.
    Raises `ModuleSpecError` naming the field at fault.
    """
    get = spec.get if isinstance(spec, Mapping) else (lambda key, default=None: getattr(spec, key, default))
    name = get("name")
    python, fmu = get("python"), get("fmu")
    params = dict(get("params") or {})
    targets = list(get("targets") or ())
    isolate, call_timeout, start_time = bool(get("isolate", False)), get("call_timeout"), get("start_time")
    if not isinstance(name, str) or not name:
        raise ModuleSpecError(f"a module spec needs a name, got {name!r}", "name")
    if python is not None and fmu is not None:
        raise ModuleSpecError(f"module {name!r} has both `python:` and `fmu:`; it is one or the other")
    if fmu is not None:
        return _make_fmu(name, fmu, base_dir, params, targets, isolate, call_timeout, start_time)
    if python is None:
        raise ModuleSpecError(f"module {name!r} needs `python: package.module:Class` (or `fmu:`)")
    for key, given in (("isolate", isolate), ("call_timeout", call_timeout is not None),
                       ("start_time", start_time is not None)):
        if given:
            raise ModuleSpecError(f"{key} applies to an FMU module (`fmu:`), not to a Python class", key)
    try:
        cls = resolve_module_class(python, ClassPolicy.of(allow_python, [base_dir] if local_modules else []))
    except ClassNotAllowedError as exc:
        raise ModuleNotAllowedError(python, allow_python, str(exc)) from None
    except DynabrainError as exc:
        raise ModuleSpecError(str(exc), "python") from None
    try:
        return cls(name, targets=targets, **params)
    except DynabrainError as exc:
        raise ModuleSpecError(str(exc), "params") from None
    except Exception as exc:
        raise ModuleSpecError(f"module {name!r} ({python}) failed to construct: {type(exc).__name__}: {exc}") from None


def _make_fmu(name: str, fmu: str, base_dir: str, params: dict[str, Any], targets: list[str], isolate: bool,
              call_timeout: Any, start_time: Any = None) -> Module:
    from ..fmu import make_fmu_module
    from ..fmu.errors import FMUError

    timeout = None
    if call_timeout is not None:
        try:
            timeout = parse_duration_ns(call_timeout, allow_frequency=False) / 1e9
            if not isolate or timeout <= 0:
                raise DynabrainError("a positive duration, for an FMU with `isolate: true`")
        except DynabrainError as exc:
            raise ModuleSpecError(f"call_timeout {call_timeout!r}: {exc}", "call_timeout") from None
    start = None
    if start_time is not None:  # the FMU's time at world time 0 (seconds)
        try:
            start = parse_duration_ns(start_time, allow_frequency=False) / 1e9
        except DynabrainError as exc:
            raise ModuleSpecError(f"start_time {start_time!r}: {exc}", "start_time") from None
    try:
        return make_fmu_module(name, fmu, base_dir=base_dir, params=params, targets=targets, isolate=isolate,
                               call_timeout=timeout, start_time=start)
    except ModuleNotFoundError as exc:  # the [fmu] extra is not installed
        missing = hint(exc)
        if missing is None:
            raise
        raise ModuleSpecError(f"module {name!r}: {missing}", "fmu") from None
    except DynabrainError as exc:
        raise ModuleSpecError(str(exc), "fmu" if isinstance(exc, FMUError) else "params") from None
