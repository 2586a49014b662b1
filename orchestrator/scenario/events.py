"""Scenario events: edits the world makes at given times.

``{at: 1s, set: {core.restitution: 0.8}}``, ``add: {module...}``, ``remove: name``,
``make: [objects]``, ``make_joint: [a, b]``, ``no_collision: [objects]``,
``place: {body: [x, y, z]}``, ``connect: [src, dst]``, ``disconnect: dst``.
One event may hold several of these; they apply in that order. Every event is checked at load.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict

from ..kernel.errors import DynabrainError
from ..kernel.world import World, as_connection, expand_names

if TYPE_CHECKING:
    from ..kernel.yamlsrc import Path
    from .model import ModuleCfg, _Builder

EVENT_KINDS = ("set", "add", "remove", "make", "make_joint", "no_collision", "place", "connect", "disconnect")


class EventCfg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    at: str | int | float
    set: dict[str, Any] | None = None
    add: ModuleCfgRef | None = None
    remove: str | None = None
    make: list[str] | None = None
    make_joint: list[str] | None = None
    no_collision: list[str] | None = None
    place: dict[str, Any] | None = None
    connect: list[Any] | None = None
    disconnect: str | None = None


def _module_cfg_type():
    from .model import ModuleCfg

    return ModuleCfg


ModuleCfgRef = Any  # the real type is resolved below, once scenario.py has defined ModuleCfg


def build_event(ev: EventCfg, world: World, builder: _Builder, path: Path) -> tuple[Callable[[World], None], str]:
    """Check an event against the world as built and return (action, label)."""
    actions: list[Callable[[World], None]] = []
    labels: list[str] = []
    for kind in EVENT_KINDS:
        value = getattr(ev, kind)
        if value is None:
            continue
        check = _CHECKS[kind]
        actions.append(check(value, world, builder, (*path, kind)))
        labels.append(kind)
    if not actions:
        raise DynabrainError("an event needs something to do: " + ", ".join(EVENT_KINDS))

    def run(w: World) -> None:
        for act in actions:
            act(w)

    return run, "+".join(labels)


def _set(value: dict[str, Any], world: World, builder: _Builder, path: Path):
    for name in value:
        if name.partition(".")[0] in builder.later_modules:
            continue  # a module an earlier event adds: checked when the event fires
        try:
            target = world.settable(name)
        except DynabrainError as exc:
            builder.report((*path, name), str(exc))
            continue
        if isinstance(target, tuple) and not target[0].param_specs()[target[1]].runtime:
            builder.report((*path, name), f"parameter {name} cannot be changed at run time")
    def apply(w: World) -> None:
        for name, val in value.items():
            w.set(name, val)

    return apply


def _add(value: Any, world: World, builder: _Builder, path: Path):
    cfg: ModuleCfg = _module_cfg_type().model_validate(value)
    builder.later_modules.add(cfg.name)
    if builder.make_module(cfg, path) is None:  # checked now; a fresh module is made at each firing
        return lambda w: None
    if cfg.name in world.modules:
        builder.report((*path, "name"), f"module name {cfg.name!r} is already used")

    def add(w: World) -> None:
        module = builder.make_module(cfg, path)
        if module is None:
            raise DynabrainError(f"module {cfg.name!r} could not be made")
        w.add_module(module, period=None if cfg.period is None else str(cfg.period),
                     connect=[as_connection(c) for c in cfg.connect])

    return add


def _remove(value: str, world: World, builder: _Builder, path: Path):
    return lambda w: w.remove_module(value)


def _objects(call: str):
    def check(value: list[str], world: World, builder: _Builder, path: Path):
        core = world.core
        if core is None:
            builder.report(path, f"{call} needs a physics core")
            return lambda w: None
        known = core.objects() if call == "make" else core.bodies()
        kind = "object" if call == "make" else "body"
        for i, name in enumerate(value):
            try:
                expand_names([name], known, kind, call)
            except DynabrainError as exc:
                builder.report((*path, i), str(exc))
        if call == "make_joint":
            if len(value) != 2:
                builder.report(path, "make_joint takes two bodies: [a, b]")
            return lambda w: w.make_joint(value[0], value[1])
        return lambda w: getattr(w, call)(value)

    return check


def _place(value: dict[str, Any], world: World, builder: _Builder, path: Path):
    core = world.core
    if core is None:
        builder.report(path, "place needs a physics core")
        return lambda w: None
    from ..kernel.suggest import did_you_mean

    for name in value:
        if name not in core.bodies():
            builder.report((*path, name), f"unknown body {name!r}" + did_you_mean(name, core.bodies()))

    def place(w: World) -> None:
        for name, pose in value.items():
            if isinstance(pose, dict):
                w.place(name, pose["pos"], pose.get("quat"))
            else:
                w.place(name, pose)

    return place


def _connect(value: list[Any], world: World, builder: _Builder, path: Path):
    conn = as_connection(value)
    return lambda w: w.connect(conn.src, conn.dst, delay=conn.delay)


def _disconnect(value: str, world: World, builder: _Builder, path: Path):
    return lambda w: w.disconnect(value)


_CHECKS = {
    "set": _set, "add": _add, "remove": _remove, "make": _objects("make"), "make_joint": _objects("make_joint"),
    "no_collision": _objects("no_collision"), "place": _place, "connect": _connect, "disconnect": _disconnect,
}
