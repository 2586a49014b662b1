"""Scenario events: edits the world makes at given times.

``{at: 1s, set: {core.restitution: 0.8}}``, ``add: {module...}``, ``remove: name``,
``make: [objects]``, ``make_joint: [a, b]``, ``no_collision: [objects]``,
``place: {body: [x, y, z]}``, ``connect: [src, dst]``, ``disconnect: dst``.
One event may hold several of these; they apply in that order. Every event is checked at load, in
time order, against the structure the events before it leave (a `Timeline`: which modules exist,
which inputs are driven), so that removing a module twice, connecting an input already driven or
disconnecting one nothing drives is refused before t=0, not at its tick.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from ..kernel.errors import DynabrainError
from ..kernel.suggest import did_you_mean
from ..kernel.units import format_duration, parse_duration_ns
from ..kernel.world import World, as_connection, expand_names
from .limits import CORE_LIMITS, Duration, check_magnitudes, param_problem, short
from .scene import parse_pose

if TYPE_CHECKING:
    from ..kernel.yamlsrc import Path
    from .model import ModuleCfg, _Builder

EVENT_KINDS = ("set", "add", "remove", "make", "make_joint", "no_collision", "place", "connect", "disconnect")


class EventCfg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    at: Duration
    """When (a time from the start, 0 or more)."""
    set: dict[str, Any] | None = None
    add: ModuleCfgRef | None = None
    remove: str | None = None
    make: list[str] | None = None
    make_joint: list[str] | None = None
    no_collision: list[str] | None = None
    place: dict[str, Any] | None = None
    connect: list[Any] | None = None
    disconnect: str | None = None


@dataclass
class Timeline:
    """The structure as the events checked so far leave it: the modules present, per driven input the
    output that drives it (names as the scenario writes them), the objects selected, the joints made."""

    modules: set[str]
    drivers: dict[str, str]
    selection: set[str] | None = None
    """The objects simulated (`make`); None without a physics core."""
    joints: set[str] = field(default_factory=set)
    """Joints made by `make_joint` events."""

    @classmethod
    def of(cls, world: World) -> Timeline:
        selection = None if world.core is None else set(world.core.selection)
        return cls(set(world.modules), {c.dst: c.src for c in world.connections}, selection)

    def module_of(self, signal: str) -> str:
        return signal.partition(".")[0]

    def connect(self, src: str, dst: str) -> str | None:
        """Record ``src -> dst``; or say why it cannot be made at this point of the run."""
        for end in (src, dst):
            module = self.module_of(end)
            if module not in self.modules:
                return f"{end}: no module {module!r} at this time" + did_you_mean(module, sorted(self.modules))
        if dst in self.drivers:
            return f"{dst} is already driven by {self.drivers[dst]} at this time; disconnect it first"
        self.drivers[dst] = src
        return None

    def disconnect(self, dst: str) -> str | None:
        if dst not in self.drivers:
            return f"no connection drives {dst!r} at this time"
        del self.drivers[dst]
        return None

    def remove(self, module: str) -> str | None:
        if module not in self.modules:
            return f"no module {module!r} at this time" + did_you_mean(module, sorted(self.modules))
        self.modules.discard(module)
        self.drivers = {d: s for d, s in self.drivers.items() if module not in (self.module_of(d), self.module_of(s))}
        return None


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
    timeline = builder.timeline
    for name, val in value.items():
        module = name.partition(".")[0]
        if module in world.modules and module not in timeline.modules:
            builder.report((*path, name), f"{name}: module {module!r} has been removed by this time")
            continue
        if name in timeline.drivers:
            builder.report((*path, name), f"{name} is driven by {timeline.drivers[name]} at this time; "
                                          "disconnect it before setting it")
            continue
        if module in builder.later_modules and module not in world.modules:
            continue  # a module an earlier event adds: its ports and parameters are checked when it fires
        try:
            target = world.settable(name)
        except DynabrainError as exc:
            builder.report((*path, name), str(exc))
            continue
        problem = _value_problem(world, target, val)
        if problem:
            builder.report((*path, name), problem)

    def apply(w: World) -> None:
        for name, val in value.items():
            w.set(name, val)

    return apply


def _value_problem(world: World, target: str | tuple[Any, str], value: Any) -> str | None:
    """What is wrong with setting ``target`` (what `World.settable` names) to ``value``, or None."""
    if isinstance(target, tuple):
        module, key = target
        spec = module.param_specs()[key]
        if not spec.runtime:
            return "this parameter cannot be changed at run time"
        return param_problem(spec, value, CORE_LIMITS.get(key) if module is world.core else None)
    current = world.get(target)  # at load: the input's start value
    try:
        arr = np.asarray(value, dtype=np.float64)
        unset = np.isnan(arr) if np.all(np.isnan(current)) else np.zeros(arr.shape, bool)
        check_magnitudes(arr[~unset], "the value")  # NaN only where it means "unset" (a body's velocity)
    except DynabrainError as exc:
        return str(exc)
    except (TypeError, ValueError):
        return f"an input takes numbers, got {short(value)}"
    if arr.shape != np.shape(current):
        return f"the input has shape {np.shape(current)}, got a value of shape {arr.shape}"
    return None


def _add(value: Any, world: World, builder: _Builder, path: Path):
    cls = _module_cfg_type()
    timeline = builder.timeline
    name = value.get("name") if isinstance(value, dict) else None
    if isinstance(name, str):  # known by name from now on, so that what uses it is not refused too
        if name in timeline.modules:
            builder.report((*path, "name"), f"module name {name!r} is already used at this time")
        builder.later_modules.add(name)
        timeline.modules.add(name)
    try:
        cfg: ModuleCfg = cls.model_validate(value)
    except ValidationError as exc:
        builder.report_validation(path, exc, cls)
        return lambda w: None
    if cfg.period is not None and parse_duration_ns(cfg.period) % world.dt_ns:
        builder.report((*path, "period"), f"period {cfg.period} is not a whole multiple of the base step "
                                          f"({format_duration(world.dt_ns)})")
    if builder.make_module(cfg, path) is None:  # checked now; a fresh module is made at each firing
        return lambda w: None
    for j, item in enumerate(cfg.connect):
        _check_connection(item, world, builder, (*path, "connect", j))

    def add(w: World) -> None:
        module = builder.make_module(cfg, path)
        if module is None:
            raise DynabrainError(f"module {cfg.name!r} could not be made")
        w.add_module(module, period=None if cfg.period is None else str(cfg.period),
                     connect=[as_connection(c) for c in cfg.connect])

    return add


def _remove(value: str, world: World, builder: _Builder, path: Path):
    if world.core is not None and value == world.core.name:
        builder.report(path, f"the physics core {value!r} cannot be removed")
    else:
        problem = builder.timeline.remove(value)
        if problem:
            builder.report(path, f"remove: {problem}")
    return lambda w: w.remove_module(value)


def _objects(call: str):
    def check(value: list[str], world: World, builder: _Builder, path: Path):
        core = world.core
        if core is None:
            builder.report(path, f"{call} needs a physics core")
            return lambda w: None
        known = core.objects() if call == "make" else core.bodies()
        kind = "object" if call == "make" else "body"
        chosen: list[str] = []
        for i, name in enumerate(value):
            try:
                chosen += [n for n in expand_names([name], known, kind, call) if n not in chosen]
            except DynabrainError as exc:
                builder.report((*path, i), str(exc))
        timeline = builder.timeline
        if call == "make":
            timeline.selection = set(chosen)
        elif call == "no_collision" and len(chosen) < 2 and len(chosen) == len(value):
            builder.report(path, f"no_collision needs at least two bodies, got {short(value)}")
        elif call == "make_joint":
            if len(value) != 2 or len(set(value)) != 2 or any(n not in known for n in value):
                builder.report(path, f"make_joint takes two different bodies by name: [a, b], got {short(value)}")
            else:
                joint = f"joint_{value[0]}_{value[1]}"
                if joint in timeline.joints:
                    builder.report(path, f"the joint {joint!r} is made already at this time")
                timeline.joints.add(joint)
            return lambda w: w.make_joint(value[0], value[1])
        return lambda w: getattr(w, call)(value)

    return check


def _place(value: dict[str, Any], world: World, builder: _Builder, path: Path):
    core = world.core
    if core is None:
        builder.report(path, "place needs a physics core")
        return lambda w: None
    poses = {}
    selection = builder.timeline.selection
    for name, pose in value.items():
        if name not in core.bodies():
            builder.report((*path, name), f"unknown body {name!r}" + did_you_mean(name, core.bodies()))
            continue
        if name not in core.objects():
            builder.report((*path, name), f"place moves a free body, and {name!r} is part of another object")
            continue
        if selection is not None and name not in selection:
            builder.report((*path, name), f"{name!r} is frozen at this time (not selected); make([...]) it "
                                          "before placing it")
            continue
        try:
            poses[name] = parse_pose(pose)
        except DynabrainError as exc:
            builder.report((*path, name), str(exc))

    def place(w: World) -> None:
        for name, (pos, quat) in poses.items():
            w.place(name, pos, quat)

    return place


def _connect(value: list[Any], world: World, builder: _Builder, path: Path):
    conn = _check_connection(value, world, builder, path)
    return lambda w: w.connect(conn.src, conn.dst, delay=conn.delay)


def _check_connection(value: Any, world: World, builder: _Builder, path: Path):
    """The connection ``value`` writes (`as_connection` raises for a wrong shape), its problems reported."""
    conn = as_connection(value)
    ends = value[:2]
    if not all(isinstance(end, str) for end in ends):
        builder.report(path, f"a connection is [source, destination], two port names, got {short(value)}")
    elif len(value) == 3 and (not isinstance(value[2], dict) or set(value[2]) - {"delay"}
                              or not isinstance(value[2].get("delay", False), bool)):
        builder.report((*path, 2), f"a connection's options are {{delay: true or false}}, got {short(value[2])}")
    elif all(_check_signal(world, builder, end, (*path, j)) for j, end in enumerate(ends)):
        problem = builder.timeline.connect(conn.src, conn.dst)
        if problem:
            builder.report(path, problem)
    return conn


def _disconnect(value: str, world: World, builder: _Builder, path: Path):
    if _check_signal(world, builder, value, path):
        problem = builder.timeline.disconnect(value)
        if problem:
            builder.report(path, problem)
    return lambda w: w.disconnect(value)


def _check_signal(world: World, builder: _Builder, name: str, path: Path) -> bool:
    """False, with the problem reported, when ``name`` is no signal of the world (the ports of a module
    events add are known when they fire)."""
    module = name.partition(".")[0]
    if module in builder.later_modules and module not in world.modules:
        return True
    try:
        world.get(name)
    except DynabrainError as exc:
        builder.report(path, str(exc))
        return False
    return True


_CHECKS = {
    "set": _set, "add": _add, "remove": _remove, "make": _objects("make"), "make_joint": _objects("make_joint"),
    "no_collision": _objects("no_collision"), "place": _place, "connect": _connect, "disconnect": _disconnect,
}
