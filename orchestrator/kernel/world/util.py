"""Small helpers the world's parts share: module specs, connections from plain values, name patterns,
calls into a module that name it when they fail, and the lock as `World.lock` hands it out."""

from __future__ import annotations

import contextlib
import fnmatch
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from ..errors import DynabrainError, ModuleError, WiringError
from ..module import Module
from ..specs import quantities
from ..structure import Connection
from ..suggest import did_you_mean

BODY_FIELDS = ("x", "y", "z", "speed", "vel", "angvel")
"""A body's fields `World.get` reads besides its signals (as a scenario's expressions do)."""


def module_spec(module: Module, period_ns: int, connections: Sequence[Connection] = ()) -> dict[str, Any]:
    """A plain description from which the same module can be made again (logs, replay, the bridge):
    the scenario's module syntax, with parameters in SI."""
    spec = dict(module.scenario_spec())  # a class path by default; an FMU module says how it is made
    spec["period"] = f"{period_ns}ns"
    if module.targets:
        spec["targets"] = list(module.targets)
    if connections:
        spec["connect"] = [[c.src, c.dst, {"delay": True}] if c.delay else [c.src, c.dst] for c in connections]
    return spec


def as_connection(value: Connection | Sequence[Any]) -> Connection:
    """A `Connection` from ``[source, destination]`` or ``[source, destination, {delay: true}]``."""
    if isinstance(value, Connection):
        return value
    if isinstance(value, str) or len(value) not in (2, 3):
        raise WiringError(f"a connection is [source, destination] or [source, destination, {{delay: true}}], "
                          f"got {value!r}")
    delay = bool(value[2].get("delay", False)) if len(value) == 3 and isinstance(value[2], dict) else False
    return Connection(str(value[0]), str(value[1]), delay)


def expand_names(names: Sequence[str], known: Sequence[str], kind: str, call: str) -> list[str]:
    """Names with glob patterns expanded against ``known``; an unknown name or empty pattern is an error."""
    out: list[str] = []
    for name in names:
        if any(ch in name for ch in "*?["):
            matched = fnmatch.filter(known, name)
            if not matched:
                raise DynabrainError(f"{call}(): pattern {name!r} matches no {kind}")
            out += [m for m in matched if m not in out]
        elif name not in known:
            raise DynabrainError(f"{call}(): unknown {kind} {name!r}" + did_you_mean(name, known))
        elif name not in out:
            out.append(name)
    return out


def names_of(objects: Iterable[str] | str) -> list[str]:
    """One name or several, as a list."""
    return [objects] if isinstance(objects, str) else [str(o) for o in objects]


def call_module(module: Module, call: str, tick: int, fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)``, a module's ``call``; an exception other than dynabrain's own becomes a
    `ModuleError` naming the module, the call and the tick."""
    try:
        return fn(*args)
    except DynabrainError:
        raise
    except Exception as exc:
        raise ModuleError(module.name, call, tick, exc) from exc


def close_quietly(module: Module) -> None:
    with contextlib.suppress(Exception):
        module.close()


def same_params(current: dict[str, Any], values: dict[str, Any]) -> dict[str, Any]:
    """``current`` itself when ``values`` holds the same parameters (an imported state's dicts are new
    objects: keeping the module's own spares it `on_param` calls for values that did not change)."""
    if current.keys() != values.keys():
        return values
    for key, value in values.items():
        mine = current[key]
        if mine is value:
            continue
        if isinstance(mine, np.ndarray) or isinstance(value, np.ndarray):
            if not (isinstance(mine, np.ndarray) and isinstance(value, np.ndarray) and mine.dtype == value.dtype
                    and np.array_equal(mine, value)):
                return values
        elif type(mine) is not type(value) or mine != value:
            return values
    return current


def world_values(value: Sequence[Any], key: str) -> list[float]:
    """A joint's axis or anchor as numbers in SI (an event's detail; the core has checked them)."""
    return [float(x) for x in quantities(value, 3, "length" if key == "anchor" else None)]


def read_only(buf: np.ndarray) -> np.ndarray:
    view = buf.view()
    view.setflags(write=False)
    return view


def nothing(*_args: Any) -> None:
    """What a world with no modules yet runs for a tick, and records after it."""


class Lock:
    """The world lock as `World.lock` hands it out: a context manager itself (``with world.lock:``) and
    callable for the lock (``with world.lock():``, ``world.lock().acquire()``)."""

    __slots__ = ("_rlock",)

    def __init__(self, rlock: Any):
        self._rlock = rlock

    def __call__(self) -> Any:
        return self._rlock

    def __enter__(self) -> Any:
        return self._rlock.__enter__()

    def __exit__(self, *exc: object) -> Any:
        return self._rlock.__exit__(*exc)
