"""Module classes named by ``"package.module:Class"`` strings, resolved in this one place.

Naming a class imports its module, and importing a module runs its top-level code, so a class path
that a scenario, a log or a bridge call carries is allowed (`ClassPolicy.refusal`) before anything
is imported. Allowed are:

- dynabrain's own module classes (`SHIPPED`: the modules under ``dynabrain.modules``, the FMU
  modules, the bridge's servo);
- the classes installed packages declare as entry points of the group ``dynabrain.modules``
  (``[project.entry-points."dynabrain.modules"] my_servo = "mypkg.servo:MyServo"``);
- classes under a package the user allowed (``--allow-python PKG``, the bridge's configured list:
  a package name, or an ``fnmatch`` pattern on the whole class path);
- modules that lie in an allowed folder (a scenario's own folder, for its local modules).

A module named ``__main__`` (a program's entry point: importing it runs the program) never is.
"""

from __future__ import annotations

import fnmatch
import importlib
import importlib.machinery
import importlib.util
import os
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from importlib import metadata as importlib_metadata

from .errors import DynabrainError
from .extras import hint
from .module import Module
from .suggest import did_you_mean

_SPEC = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")

CORES = {
    "mujoco": "dynabrain.modules.mujoco.core:MujocoCore",
    "exudyn": "dynabrain.modules.exudyn.core:ExudynCore",
}

SHIPPED = ("dynabrain.modules", "dynabrain.orchestrator.fmu", "dynabrain.bridge.servo")
"""The packages (and modules) of dynabrain that hold its module classes: any module under them may be named."""
ENTRY_POINT_GROUP = "dynabrain.modules"
"""The entry-point group under which an installed package declares its module classes."""
HOW_TO_ALLOW = ("to allow it, pass --allow-python {package} (dynabrain serve: --allow-python {package}), or "
                "declare the class as a `dynabrain.modules` entry point of an installed package")


@lru_cache(maxsize=1)
def registered() -> frozenset[str]:
    """The class paths installed packages declare in the ``dynabrain.modules`` entry-point group (read
    from their metadata: nothing is imported)."""
    try:
        points = importlib_metadata.entry_points(group=ENTRY_POINT_GROUP)
    except Exception:  # a broken distribution's metadata must not stop dynabrain
        return frozenset()
    return frozenset(p.value.replace(" ", "") for p in points if _SPEC.match(p.value.replace(" ", "")))


@dataclass(frozen=True)
class ClassPolicy:
    """Which class paths may be imported (see the module docstring): dynabrain's own and the registered
    ones always, plus ``packages`` (names or ``fnmatch`` patterns) and ``folders`` the user allowed."""

    packages: tuple[str, ...] = ()
    folders: tuple[str, ...] = ()

    @classmethod
    def of(cls, packages: Sequence[str] = (), folders: Sequence[str | os.PathLike[str]] = ()) -> ClassPolicy:
        return cls(tuple(packages), tuple(os.path.abspath(os.fspath(f)) for f in folders))

    def refusal(self, spec: str) -> str | None:
        """Why ``spec`` may not be imported (with how to allow it), or None when it may. Imports nothing."""
        if not isinstance(spec, str) or not _SPEC.match(spec):
            return f"{spec!r} is not of the form 'package.module:Class'"
        module_name = spec.partition(":")[0]
        if "__main__" in module_name.split("."):
            return (f"module class {spec!r} is refused: {module_name!r} is a program's entry point (a __main__ "
                    "module runs the program when imported), never a module's home")
        if (_under(module_name, SHIPPED) or spec in registered() or self._package_allows(spec, module_name)
                or self.local_folder(module_name) is not None):
            return None
        top = module_name.split(".")[0]
        return f"module class {spec!r} is not allowed: it is neither dynabrain's nor registered; " + \
            HOW_TO_ALLOW.format(package=top)

    def _package_allows(self, spec: str, module_name: str) -> bool:
        for pattern in self.packages:
            if any(c in pattern for c in "*?["):
                if fnmatch.fnmatchcase(spec, pattern):
                    return True
            elif _under(module_name, (pattern,)) or spec == pattern:
                return True
        return False

    def local_folder(self, module_name: str) -> str | None:
        """The allowed folder that holds ``module_name``'s top-level module or package, if one does
        (found by looking at the folder's files; nothing is imported)."""
        top = module_name.split(".")[0]
        for folder in self.folders:
            found = importlib.machinery.PathFinder.find_spec(top, [folder])
            if found is not None and found.origin is not None and os.path.isfile(found.origin):
                return folder
        return None


def _under(module_name: str, packages: Sequence[str]) -> bool:
    return any(module_name == p or module_name.startswith(p + ".") for p in packages)


def resolve_module_class(spec: str, policy: ClassPolicy, base: type = Module) -> type:
    """The class ``spec`` names, when ``policy`` allows it: refused (`DynabrainError`, saying how to
    allow it) before its module is imported otherwise."""
    refusal = policy.refusal(spec)
    if refusal is not None:
        raise ClassNotAllowedError(refusal, spec)
    folder = policy.local_folder(spec.partition(":")[0])
    if folder is not None and not _under(spec.partition(":")[0], SHIPPED):
        _import_local(spec.partition(":")[0].split(".")[0], folder)
    return resolve_class(spec, base)


class ClassNotAllowedError(DynabrainError):
    """A class path that a `ClassPolicy` refuses; nothing was imported."""

    def __init__(self, message: str, spec: str):
        super().__init__(message)
        self.spec = spec


def _import_local(top: str, folder: str) -> None:
    """Import the top-level module ``top`` from ``folder`` (a scenario's own module), unless one of that
    name is loaded already (then `resolve_class` uses that one, which must hold the class)."""
    if top in sys.modules:
        return
    found = importlib.machinery.PathFinder.find_spec(top, [folder])
    if found is None or found.loader is None:
        return
    module = importlib.util.module_from_spec(found)
    sys.modules[top] = module
    try:
        found.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(top, None)
        raise


def resolve_class(spec: str, base: type = Module) -> type:
    """Import ``package.module:Class`` and check it is a subclass of ``base``. No policy: for class
    paths written in dynabrain's own code (`CORES`); what a file or a client names goes through
    `resolve_module_class`."""
    if not isinstance(spec, str) or not _SPEC.match(spec):
        raise DynabrainError(f"{spec!r} is not of the form 'package.module:Class'")
    module_name, _, attr = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = hint(exc)
        if missing is not None:
            raise missing from None
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
