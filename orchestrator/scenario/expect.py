"""Expectations: small Python expressions over the world, checked at their times.

Names an expression may use: ``t`` (seconds); a body of the scene (``aa.z``, ``aa.pos``,
``aa.quat``, ``aa.vel``, ``aa.speed``, ``aa.x``, ``aa.y``); a module (``meter.apexes`` reads the
output or input port, ``core.friction`` a parameter); functions ``abs min max sqrt norm all any
round len isnan``. Names are checked when the scenario loads.
"""

from __future__ import annotations

import ast
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError
from ..kernel.suggest import did_you_mean

FUNCTIONS: dict[str, Any] = {
    "abs": abs, "min": min, "max": max, "sqrt": math.sqrt, "norm": np.linalg.norm, "all": all, "any": any,
    "round": round, "len": len, "isnan": math.isnan, "pi": math.pi,
}
BODY_FIELDS = ("x", "y", "z", "pos", "quat", "vel", "angvel", "speed")


class BodyProxy:
    """A body's pose and velocity, read from the physics core."""

    def __init__(self, core: Any, name: str):
        self._core, self._name = core, name

    def __getattr__(self, key: str) -> Any:
        if key in ("x", "y", "z"):
            return float(self._core.body_pose(self._name)[0]["xyz".index(key)])
        if key == "pos":
            return self._core.body_pose(self._name)[0]
        if key == "quat":
            return self._core.body_pose(self._name)[1]
        if key == "vel":
            return self._core.body_velocity(self._name)[0]
        if key == "angvel":
            return self._core.body_velocity(self._name)[1]
        if key == "speed":
            return float(np.linalg.norm(self._core.body_velocity(self._name)[0]))
        raise AttributeError(f"body {self._name!r} has no field {key!r}" + did_you_mean(key, BODY_FIELDS))


class ModuleProxy:
    """A module's ports and parameters by attribute (``servo.kp``, ``meter.apexes``); a port whose
    name has dots reads as a chain (``core.floor_tilt.q``)."""

    def __init__(self, world: Any, name: str):
        self._world, self._name = world, name

    def __getattr__(self, key: str) -> Any:
        name = f"{self._name}.{key}"
        try:
            return self._world.get(name)
        except DynabrainError:
            if any(s.startswith(name + ".") for s in self._world.signals()):
                return ModuleProxy(self._world, name)
            raise


@dataclass
class Expectation:
    """``that`` must hold at tick ``tick`` (or every tick in ``[start, end]``)."""

    that: str
    start: int
    end: int
    label: str
    line: int | None = None
    passed: bool | None = None
    detail: str = ""

    def __post_init__(self) -> None:
        try:
            self._code = compile(ast.parse(self.that, mode="eval"), f"<expect {self.that}>", "eval")
        except SyntaxError as exc:
            raise DynabrainError(f"expression {self.that!r} is not valid: {exc.msg}") from None

    def names(self) -> list[tuple[str, str | None]]:
        """(name, dotted attribute chain or None) pairs the expression reads: ``core.floor_tilt.q``
        gives ("core", "floor_tilt.q")."""
        out: list[tuple[str, str | None]] = []
        tree = ast.parse(self.that, mode="eval")
        inner = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and id(node) not in inner:
                chain, base = [], node
                while isinstance(base, ast.Attribute):
                    chain.append(base.attr)
                    inner.add(id(base))
                    base = base.value
                if isinstance(base, ast.Name):
                    out.append((base.id, ".".join(reversed(chain))))
                    inner.add(id(base))
        for node in ast.walk(tree):
            if isinstance(node, ast.Name) and id(node) not in inner:
                out.append((node.id, None))
        return list(dict.fromkeys(out))

    def check(self, world: Any, namespace: dict[str, Any]) -> bool:
        namespace["t"] = world.time
        try:
            value = eval(self._code, {"__builtins__": {}}, namespace)  # names checked at load
            ok = bool(np.all(value))
        except Exception as exc:
            self.passed, self.detail = False, f"error evaluating: {type(exc).__name__}: {exc}"
            return False
        if not ok:
            self.detail = f"false at t={world.time:.6g}s ({_explain(self.that, namespace)})"
            self.passed = False
        elif self.passed is None and world.tick_count >= self.end:
            self.passed = True
        return ok


def _explain(expr: str, namespace: dict[str, Any]) -> str:
    """Values of the attribute reads in ``expr``, to show why it failed."""
    parts = []
    seen = set()
    for node in ast.walk(ast.parse(expr, mode="eval")):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            text = f"{node.value.id}.{node.attr}"
            if text in seen:
                continue
            seen.add(text)
            try:
                value = eval(compile(ast.Expression(node), "<x>", "eval"), {"__builtins__": {}}, namespace)
                parts.append(f"{text} = {np.round(value, 6) if isinstance(value, np.ndarray) else _fmt(value)}")
            except Exception:
                pass
    return ", ".join(parts) or "no values"


def _fmt(value: Any) -> str:
    return f"{value:.6g}" if isinstance(value, float) else repr(value)


class _Namespace(dict):
    """The names an expression sees; a module added after the namespace was made is found too."""

    def __init__(self, world: Any):
        super().__init__(FUNCTIONS)
        self._world = world

    def __missing__(self, key: str) -> Any:
        if key in self._world.modules:
            self[key] = ModuleProxy(self._world, key)
            return self[key]
        raise KeyError(key)


def namespace_for(world: Any) -> dict[str, Any]:
    ns = _Namespace(world)
    core = world.core
    if core is not None:
        for body in core.bodies():
            ns[body] = BodyProxy(core, body)
    for name in world.modules:
        ns[name] = ModuleProxy(world, name)
    return ns


def check_names(exp: Expectation, world: Any, later: set[str] = frozenset()) -> list[str]:
    """Problems with the names an expectation reads (unknown bodies, modules, ports, params).
    ``later`` names modules the scenario's events add: their ports are checked when they exist."""
    ns = namespace_for(world)
    problems = []
    for name, attr in exp.names():
        if name in later and name not in ns:
            continue
        if name not in ns and name != "t":
            problems.append(f"unknown name {name!r} in {exp.that!r}" + did_you_mean(name, [*ns, *later, "t"]))
        elif attr is not None and isinstance(ns.get(name), BodyProxy) and attr.split(".")[0] not in BODY_FIELDS:
            problems.append(f"body {name!r} has no field {attr!r}" + did_you_mean(attr, BODY_FIELDS))
        elif attr is not None and isinstance(ns.get(name), ModuleProxy):
            problem = _check_chain(world, name, attr.split("."))
            if problem:
                problems.append(f"in {exp.that!r}: {problem}")
    return problems


def _check_chain(world: Any, module: str, parts: list[str]) -> str | None:
    """None when some prefix of ``module.part1.part2...`` is a signal or parameter."""
    first = None
    for end in range(len(parts), 0, -1):
        try:
            world.get(".".join([module, *parts[:end]]))
            return None
        except DynabrainError as exc:
            first = first or str(exc)
    return first
