"""Module classes named by ``"package.module:Class"`` strings, resolved in this one place."""

from __future__ import annotations

import importlib
import re

from .errors import DynabrainError
from .module import Module
from .suggest import did_you_mean

_SPEC = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")

CORES = {
    "mujoco": "dynabrain.modules.mujoco.core:MujocoCore",
    "exudyn": "dynabrain.modules.exudyn.core:ExudynCore",
}


def resolve_class(spec: str, base: type = Module) -> type:
    """Import ``package.module:Class`` and check it is a subclass of ``base``."""
    if not isinstance(spec, str) or not _SPEC.match(spec):
        raise DynabrainError(f"{spec!r} is not of the form 'package.module:Class'")
    module_name, _, attr = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            raise DynabrainError(f"cannot import {module_name!r}: no module named {exc.name!r}") from None
        raise DynabrainError(f"importing {module_name!r} failed: {exc}") from exc
    except Exception as exc:
        raise DynabrainError(f"importing {module_name!r} failed: {type(exc).__name__}: {exc}") from exc
    obj = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            names = [n for n in dir(obj) if not n.startswith("_")]
            raise DynabrainError(f"{module_name!r} has no class {attr!r}" + did_you_mean(part, names))
        obj = getattr(obj, part)
    if not isinstance(obj, type) or not issubclass(obj, base):
        raise DynabrainError(f"{spec!r} is not a {base.__name__} subclass")
    return obj


def resolve_core(engine: str) -> type:
    """The physics-core class for an engine name (``mujoco``, ``exudyn``)."""
    if engine not in CORES:
        raise DynabrainError(f"unknown core {engine!r}" + did_you_mean(engine, CORES) + f"; known: {', '.join(CORES)}")
    from .core import PhysicsCore

    try:
        return resolve_class(CORES[engine], PhysicsCore)
    except DynabrainError as exc:
        raise DynabrainError(f"core {engine!r} is not available: {exc}") from None
