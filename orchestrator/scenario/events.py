"""Scenario events: edits the world makes at given times.

``{at: 1s, set: {core.restitution: 0.8}}``, ``add_body: {box: {name: b, size: [...], ...}}`` (a body,
written as a scene item), ``add: {module...}``, ``remove: name``, ``make: [objects]`` (the others frozen)
or ``make: {objects: [...], others: absent}`` (the others out of the simulation: `World.make`),
``make_joint: [a, b]`` (a weld) or ``{a: x, b: y, kind: hinge, axis: [0, 1, 0], anchor: [0, 0, 1m]}``,
``no_collision: [objects]``, ``place: {body: [x, y, z]}``, ``connect: [src, dst]``, ``disconnect: dst``,
``remove_body: name``, ``remove_joint: name`` (a joint a ``make_joint`` event made: ``joint_<a>_<b>``
unless named; a grasp let go). ``set`` also takes a body's own ``core.<body>.friction`` and ``.restitution``.
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

from ..kernel import edits
from ..kernel.bodies import joint_kind
from ..kernel.core import MAKE_OTHERS
from ..kernel.errors import DynabrainError, UnitError
from ..kernel.suggest import did_you_mean
from ..kernel.units import format_duration, parse_duration_ns
from ..kernel.world import World, as_connection, expand_names
from .limits import CORE_LIMITS, MAX_FRICTION, MAX_MASS_KG, Duration, bounded, check_magnitudes, param_problem, short
from .scene import parse_body, parse_pose, parse_vector

if TYPE_CHECKING:
    from ..kernel.yamlsrc import Path
    from .model import ModuleCfg, _Builder

EVENT_KINDS = ("add_body", "set", "add", "remove", "make", "make_joint", "no_collision", "place", "connect",
               "disconnect", "remove_body", "remove_joint")


class EventCfg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    at: Duration
    """When (a time from the start, 0 or more)."""
    set: dict[str, Any] | None = None
    add: ModuleCfgRef | None = None
    remove: str | None = None
    make: list[str] | dict[str, Any] | None = None
    make_joint: list[str] | dict[str, Any] | None = None
    no_collision: list[str] | None = None
    place: dict[str, Any] | None = None
    connect: list[Any] | None = None
    disconnect: str | None = None
    add_body: dict[str, Any] | None = None
    remove_body: str | None = None
    remove_joint: str | None = None


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
    bodies: dict[str, str | None] = field(default_factory=dict)
    """Every body present -> the object it belongs to (None: it is one), in body order."""
    added: set[str] = field(default_factory=set)
    """Bodies `add_body` events add (their ports are checked when they exist)."""

    @classmethod
    def of(cls, world: World) -> Timeline:
        core = world.core
        selection = None if core is None else set(core.selection)
        out = cls(set(world.modules), {c.dst: c.src for c in world.connections}, selection)
        for body in core.bodies() if core is not None else ():
            top = core.body_info(body).parent
            while top is not None and core.body_info(top).parent is not None:
                top = core.body_info(top).parent
            out.bodies[body] = top
        return out

    def objects(self) -> list[str]:
        return [b for b, top in self.bodies.items() if top is None]

    def body_port(self, name: str, core: str | None) -> bool:
        """Whether ``name`` is a port of the core (``core.<body>.<port>``) of a body an event adds."""
        rest = name[len(core) + 1:] if core is not None and name.startswith(f"{core}.") else None
        return rest is not None and rest.rpartition(".")[0] in self.added

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


def _applying(*records: edits.Edit) -> Callable[[World], None]:
    """The action of an event made of these edits (`kernel.edits`), applied in order."""
    def apply(w: World) -> None:
        for record in records:
            record.apply(w)

    return apply


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
        material = _material(name, world, timeline)
        if material is not None:
            problem = _material_problem(material, val)
            if problem:
                builder.report((*path, name), problem)
            continue
        if timeline.body_port(name, world.core.name if world.core is not None else None):
            continue  # a port of a body an earlier event adds: checked when it fires
        try:
            target = world.settable(name)
        except DynabrainError as exc:
            builder.report((*path, name), str(exc))
            continue
        problem = _value_problem(world, target, val)
        if problem:
            builder.report((*path, name), problem)

    return _applying(*(edits.Set(name, val) for name, val in value.items()))


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
    return _applying(edits.RemoveModule(value))


def _objects(call: str):
    def check(value: list[str], world: World, builder: _Builder, path: Path):
        core = world.core
        if core is None:
            builder.report(path, f"{call} needs a physics core")
            return lambda w: None
        timeline = builder.timeline
        known = timeline.objects() if call == "make" else list(timeline.bodies)
        kind = "object" if call == "make" else "body"
        if call == "make_joint":
            return _make_joint(value, world, builder, path, known)
        others = "frozen"
        if call == "make" and isinstance(value, dict):
            value, others = _make_fields(value, builder, path)
            path = (*path, "objects")
        chosen: list[str] = []
        for i, name in enumerate(value):
            try:
                chosen += [n for n in expand_names([name], known, kind, call) if n not in chosen]
            except DynabrainError as exc:
                builder.report((*path, i), str(exc))
        if call == "make":
            timeline.selection = set(chosen)
        elif call == "no_collision" and len(chosen) < 2 and len(chosen) == len(value):
            builder.report(path, f"no_collision needs at least two bodies, got {short(value)}")
        if call == "make":
            return _applying(edits.Make(tuple(value), others))
        return _applying(edits.NoCollision(tuple(value)))

    return check


_MAKE_KEYS = ("objects", "others")


def _make_fields(value: dict, builder: _Builder, path: Path) -> tuple[list[str], str]:
    """``make: {objects: [...], others: frozen | absent}``: the names and the mode, each checked."""
    for key in value:
        if key not in _MAKE_KEYS:
            builder.report((*path, key), f"unknown key {key!r}" + did_you_mean(str(key), _MAKE_KEYS)
                           + f"; make takes {', '.join(_MAKE_KEYS)}")
    objects = value.get("objects")
    if isinstance(objects, str):
        objects = [objects]
    if not isinstance(objects, list) or not all(isinstance(o, str) for o in objects):
        builder.report((*path, "objects"), f"make: objects is a list of object names, got {short(objects)}")
        objects = []
    others = value.get("others", "frozen")
    if others not in MAKE_OTHERS:
        builder.report((*path, "others"), f"make: unknown mode {others!r}" + did_you_mean(str(others), MAKE_OTHERS)
                       + f"; one of: {', '.join(MAKE_OTHERS)}")
        others = "frozen"
    return objects, others


_JOINT_KEYS = ("a", "b", "kind", "axis", "anchor", "name")


def _make_joint(value: Any, world: World, builder: _Builder, path: Path, known: list[str]):
    """``[a, b]`` (a weld) or ``{a, b, kind, axis, anchor, name}``, checked against the bodies present."""
    fields = dict(zip(("a", "b"), value, strict=False)) if isinstance(value, list) else dict(value)
    if isinstance(value, list) and len(value) != 2:
        builder.report(path, f"make_joint takes two different bodies by name: [a, b], got {short(value)}")
        return lambda w: None
    for key in fields:
        if key not in _JOINT_KEYS:
            builder.report((*path, key), f"unknown key {key!r}" + did_you_mean(str(key), _JOINT_KEYS)
                           + f"; make_joint takes {', '.join(_JOINT_KEYS)}")
    a, b = fields.get("a"), fields.get("b")
    if a == b or any(not isinstance(n, str) or n not in known for n in (a, b)):
        where = path if isinstance(value, list) else (*path, "b" if a == b else "a" if a not in known else "b")
        listed = ", ".join(known[:20]) + (", ..." if len(known) > 20 else "")
        builder.report(where, f"make_joint: a joint between a body and itself ({short(a)}); it takes two different "
                       "bodies" if a == b else f"make_joint takes two bodies by name, got {short(a)} and {short(b)}; "
                       f"bodies at this time: {listed}")
        return lambda w: None
    kwargs: dict[str, Any] = {}
    try:
        kind = joint_kind(fields.get("kind", "weld"))
        made = getattr(world.core, "MADE_JOINTS", ("weld",))
        if kind not in made:
            raise UnitError(f"the {world.core.ENGINE} core cannot make a {kind} joint (it makes: {', '.join(made)})")
        kwargs["kind"] = kind
    except UnitError as exc:
        builder.report((*path, "kind"), str(exc))
    for key, dim in (("axis", None), ("anchor", "length")):
        if key in fields:
            try:
                if kwargs.get("kind") == "weld" or (key == "axis" and kwargs.get("kind") == "ball"):
                    raise UnitError(f"a {kwargs['kind']} joint takes no {key}")
                kwargs[key] = parse_vector(fields[key], 3, dim)
                if key == "axis" and not any(kwargs[key]):
                    raise UnitError("the axis cannot be zero")
            except (DynabrainError, TypeError, ValueError) as exc:
                builder.report((*path, key), str(exc))
    name = fields.get("name")
    if name is not None and not isinstance(name, str):
        builder.report((*path, "name"), f"a joint's name is a string, got {short(name)}")
    joint = name or f"joint_{a}_{b}"
    if joint in builder.timeline.joints:
        builder.report(path, f"the joint {joint!r} is made already at this time")
    builder.timeline.joints.add(joint)
    return _applying(edits.MakeJoint(a, b, name, kwargs.get("kind", "weld"), kwargs.get("axis"), kwargs.get("anchor")))


def _material(name: str, world: World, timeline: Timeline) -> tuple[str, str] | None:
    """(body, friction, restitution or mass) when ``name`` is a body's own coefficient or mass
    (``core.<body>.friction``)."""
    core = world.core
    if core is None or not name.startswith(f"{core.name}."):
        return None
    body, _, key = name[len(core.name) + 1:].rpartition(".")
    return (body, key) if key in ("friction", "restitution", "mass") and body in timeline.bodies else None


def _material_problem(material: tuple[str, str], value: Any) -> str | None:
    if value is None:
        return None  # the core's coefficient again
    high = {"restitution": 1.0, "mass": MAX_MASS_KG}.get(material[1], MAX_FRICTION)
    try:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UnitError(f"{material[1]} is a number (or null: the core's), got {short(value)}")
        if material[1] == "mass" and not value > 0:
            raise UnitError(f"a body's mass is above 0 kg, got {short(value)}")
        bounded(float(value), material[1], 0.0, high)
    except UnitError as exc:
        return str(exc)
    return None


def _add_body(value: dict[str, Any], world: World, builder: _Builder, path: Path):
    timeline = builder.timeline
    if world.core is None:
        builder.report(path, "add_body needs a physics core")
        return lambda w: None
    spec, problems = parse_body(value, builder.src, path, builder.sc.dir)
    builder.problems += problems
    if spec is None:
        return lambda w: None
    if spec.name in timeline.bodies or spec.name in world.core.joints():
        shape = next(iter(value))
        builder.report((*path, shape, "name"), f"add_body: a body named {spec.name!r} exists at this time")
        return lambda w: None
    timeline.bodies[spec.name] = None
    timeline.added.add(spec.name)
    if timeline.selection is not None:
        timeline.selection.add(spec.name)  # a new body is simulated
    builder.later_modules.add(spec.name)  # (so that expectations may read it)
    return _applying(edits.AddBody(spec))


def _remove_joint(value: str, world: World, builder: _Builder, path: Path):
    """A joint made at run time by an earlier event, removed (checked against the joints made by then)."""
    joints = builder.timeline.joints
    if world.core is None:
        builder.report(path, "remove_joint needs a physics core")
    elif value not in joints:
        made = ", ".join(sorted(joints)) or "none"
        builder.report(path, f"remove_joint: no joint {value!r} made by an earlier event" + did_you_mean(value, joints)
                       + f"; joints made by then: {made}")
    else:
        joints.discard(value)
    return _applying(edits.RemoveJoint(value))


def _remove_body(value: str, world: World, builder: _Builder, path: Path):
    timeline = builder.timeline
    core = world.core
    objects = timeline.objects()
    if core is None:
        builder.report(path, "remove_body needs a physics core")
    elif value not in objects:
        what = f"{value!r} is part of object {timeline.bodies[value]!r}" if value in timeline.bodies else \
            f"no object {value!r} at this time" + did_you_mean(str(value), objects)
        builder.report(path, f"remove_body: {what}")
    elif core.scene.model and value not in timeline.added:
        builder.report(path, f"remove_body: {value!r} comes from the model file; bodies added at run time and the "
                             "primitives of a scene can be removed")
    else:
        timeline.bodies = {b: top for b, top in timeline.bodies.items() if value not in (b, top)}
        timeline.added.discard(value)
        if timeline.selection is not None:
            timeline.selection.discard(value)
    return _applying(edits.RemoveBody(value))


def _place(value: dict[str, Any], world: World, builder: _Builder, path: Path):
    core = world.core
    if core is None:
        builder.report(path, "place needs a physics core")
        return lambda w: None
    poses = {}
    selection = builder.timeline.selection
    bodies = builder.timeline.bodies
    for name, pose in value.items():
        if name not in bodies:
            builder.report((*path, name), f"unknown body {name!r} at this time" + did_you_mean(name, list(bodies)))
            continue
        if bodies[name] is not None:
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

    return _applying(*(edits.Place(name, pos, quat) for name, (pos, quat) in poses.items()))


def _connect(value: list[Any], world: World, builder: _Builder, path: Path):
    conn = _check_connection(value, world, builder, path)
    return _applying(edits.Connect(conn.src, conn.dst, conn.delay))


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
    return _applying(edits.Disconnect(value))


def _check_signal(world: World, builder: _Builder, name: str, path: Path) -> bool:
    """False, with the problem reported, when ``name`` is no signal of the world (the ports of a module
    events add are known when they fire)."""
    module = name.partition(".")[0]
    if module in builder.later_modules and module not in world.modules:
        return True
    if builder.timeline.body_port(name, world.core.name if world.core is not None else None):
        return True  # a port of a body an event adds
    try:
        world.get(name)
    except DynabrainError as exc:
        builder.report(path, str(exc))
        return False
    return True


_CHECKS = {
    "set": _set, "add": _add, "remove": _remove, "make": _objects("make"), "make_joint": _objects("make_joint"),
    "no_collision": _objects("no_collision"), "place": _place, "connect": _connect, "disconnect": _disconnect,
    "add_body": _add_body, "remove_body": _remove_body, "remove_joint": _remove_joint,
}
