"""The FMU adapter: FMI 1.0 / 2.0 / 3.0 co-simulation FMUs (and FMI 3.0 scheduled execution) as
modules, and FMU authoring.

    module = make_fmu_module("servo", "fmus/servo", base_dir=".", params={"kp": 80.0}, targets=[])
    world.add_module(module)

Layers, bottom up: `api` (one method per FMI call, one status checkpoint; `api1` for FMI 1.0), `fastpath` (a step in
one crossing into C), `states` (FMU states for history), `session` (one instance's life),
`module` (the Module facade), `isolate` / `worker` (an FMU in its own process). Authoring: `spec`
(fmu.yaml), `codegen` (`codegen1`: FMI 1.0), `build` (compile, package, cache), `check` (`check_fmu`;
`checkproc`: in a child process), `scaffold`.
"""

from __future__ import annotations

from typing import Any

from ..kernel.errors import DynabrainError
from ..kernel.module import Module
from .errors import (
    FMUBuildError,
    FMUCallError,
    FMUCrashError,
    FMUDiscardError,
    FMUError,
    FMUTerminatedError,
    FMUTimeoutError,
    FMUUnusableError,
)

__all__ = ["FMUBuildError", "FMUCallError", "FMUCrashError", "FMUDiscardError", "FMUError", "FMUTerminatedError",
           "FMUTimeoutError", "FMUUnusableError", "load_fmu_info", "make_fmu_module"]


def load_fmu_info(fmu: str, *, base_dir: str = "."):
    """Resolve ``fmu`` (a ``.fmu`` file or a source folder, ``@fmi3`` to pick a version), build it
    if it is a source folder, and read its model description."""
    from .build import ensure_built
    from .info import read_fmu_info
    from .paths import resolve, split_version

    ref, version = split_version(fmu)
    path = resolve(ref, base_dir)
    return read_fmu_info(ensure_built(path, version), label=fmu)


def make_fmu_module(name: str, fmu: str, *, base_dir: str, params: dict[str, Any], targets: list[str],
                    isolate: bool = False, call_timeout: float | None = None,
                    start_time: float | None = None) -> Module:
    """A module for the FMU at ``fmu`` (a ``.fmu`` file or a source folder, relative to ``base_dir``
    or one of its parent folders). ``isolate``: run it in a process of its own; ``call_timeout``
    (seconds, isolated only): how long one call may take before the process is killed;
    ``start_time`` (seconds): the FMU's time at world time 0, instead of its description's
    ``DefaultExperiment.startTime``. Variables not on the bus (strings, binaries as inputs and
    outputs) are listed once, as a warning of the ``dynabrain.fmu`` logger."""
    if call_timeout is not None and not isolate:
        raise FMUError(f"module {name!r}: call_timeout applies to an isolated FMU (isolate: true)")
    info = load_fmu_info(fmu, base_dir=base_dir)
    _check_params(name, info, params)
    from .module import FMUModule, list_not_on_bus

    list_not_on_bus(info)
    if isolate:
        from .isolate import CALL_TIMEOUT_S, IsolatedFMUModule

        return IsolatedFMUModule(name, info, source=fmu, targets=targets, start_time=start_time,
                                 call_timeout=CALL_TIMEOUT_S if call_timeout is None else call_timeout, **params)
    return FMUModule(name, info, source=fmu, targets=targets, start_time=start_time, **params)


def _check_params(name: str, info: Any, params: dict[str, Any]) -> None:
    """A parameter that names an input or output gets a message saying what it is."""
    ports = {s.name: s.kind for s in (*info.inputs, *info.outputs)}
    for key in params:
        if key in ports:
            raise DynabrainError(f"module {name!r}: {key!r} is an {ports[key]} of {info.label}, not a parameter; "
                                 + ("connect it or set it with world.set" if ports[key] == "input" else
                                    "outputs are computed by the FMU"))
