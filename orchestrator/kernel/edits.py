"""Edits as typed records: one frozen dataclass per kind of change a world takes while it runs.

The world tells its observers each edit it made as one of these (`WorldEvent.edit`; a log writes its
``kind`` and `detail`), a scenario's events are made of them, and ``replay --verify`` makes a
recorded one again with `edit_of` and `Edit.apply`. An edit as told is the edit as done: names
expanded (``make``), a joint's name chosen, a body's coefficients as they now are. A new kind of edit
is one class here (and its World call).

`detail` gives plain values (lists, numbers, strings: what JSON and a log hold) and `from_detail`
takes them back; a recorded detail that lacks a field is refused naming the kind and the field, and
nothing in a detail runs code (a module is made only by the factory the caller allows).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from .errors import DynabrainError
from .specs import BodySpec, BodySpecError, body_detail, body_from_detail

if TYPE_CHECKING:
    from .module import Module
    from .world import World

ModuleMaker = Callable[[dict[str, Any]], "Module"]


class EditFormatError(DynabrainError):
    """A recorded edit that cannot be read back: an unknown kind, or a detail without a field it needs."""


@dataclass(frozen=True)
class Edit:
    """The base of every edit: its ``kind`` (the event's name) and how it crosses as plain values."""

    kind: ClassVar[str] = ""

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        """Make this edit on ``world`` (its World call). ``make_module``: how `AddModule` makes its module."""
        raise NotImplementedError

    def detail(self) -> dict[str, Any]:
        """The edit as plain values (an event's detail)."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def needs(cls) -> tuple[str, ...]:
        """The fields a recorded detail must hold (the others have defaults)."""
        return tuple(f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING
                     and f.default_factory is dataclasses.MISSING)

    @classmethod
    def from_detail(cls, detail: dict[str, Any]) -> Edit:
        """The edit of a detail (`detail`'s output, or a log's); a missing field raises `EditFormatError`."""
        if not isinstance(detail, dict):
            raise EditFormatError(f"a recorded {cls.kind} is a mapping of its fields, got {type(detail).__name__}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        missing = [n for n in cls.needs() if n not in detail]
        if missing:
            raise EditFormatError(f"a recorded {cls.kind} lacks {', '.join(missing)}")
        return cls(**{n: _field_value(v, fields[n]) for n, v in detail.items() if n in fields})


def _plain(value: Any) -> Any:
    return [_plain(v) for v in value] if isinstance(value, tuple) else value


def _field_value(value: Any, f: dataclasses.Field) -> Any:
    """A detail's value as a record field: a list becomes a tuple where the field is one (records are
    frozen); other values are kept as recorded (an input's value, a module's spec)."""
    return tuple(value) if isinstance(value, list) and str(f.type).startswith("tuple") else value


# -- structure ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AddModule(Edit):
    """A module added, made from its spec (the scenario's module syntax, parameters in SI)."""

    kind: ClassVar[str] = "module_added"
    module: str
    spec: dict[str, Any]

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        maker = make_module or world.module_factory
        if maker is None:
            raise DynabrainError(f"module {self.module!r} cannot be made again: the world has no module_factory "
                                 "(a world from load_world has one)")
        spec = self.spec
        world.add_module(maker(spec), period=spec.get("period"), connect=spec.get("connect", ()))

    @classmethod
    def needs(cls) -> tuple[str, ...]:
        return ("spec",)

    @classmethod
    def from_detail(cls, detail: dict[str, Any]) -> Edit:
        spec = detail.get("spec") if isinstance(detail, dict) else None
        if not isinstance(spec, dict):
            raise EditFormatError(f"its spec is no mapping: {spec!r:.80}")
        return cls(str(detail.get("module", spec.get("name"))), spec)

    def detail(self) -> dict[str, Any]:
        return {"module": self.module, "spec": self.spec}


@dataclass(frozen=True)
class RemoveModule(Edit):
    kind: ClassVar[str] = "module_removed"
    module: str

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.remove_module(self.module)


@dataclass(frozen=True)
class Connect(Edit):
    kind: ClassVar[str] = "connect"
    src: str
    dst: str
    delay: bool = False

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.connect(self.src, self.dst, delay=bool(self.delay))


@dataclass(frozen=True)
class Disconnect(Edit):
    kind: ClassVar[str] = "disconnect"
    dst: str

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.disconnect(self.dst)


@dataclass(frozen=True)
class DeclareLoop(Edit):
    """Modules iterated to agreement each macro step (`World.iterate`)."""

    kind: ClassVar[str] = "iterate_declared"
    loop: str
    modules: tuple[str, ...]
    tolerance: float = 1e-9
    max_iterations: int = 50

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        return world.iterate(self.modules, name=self.loop, tolerance=self.tolerance,
                             max_iterations=self.max_iterations)


# -- values ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Set(Edit):
    """An input set (``module.port``); applied by `World.set`, which also takes a parameter's name."""

    kind: ClassVar[str] = "set"
    name: str
    value: Any

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.set(self.name, self.value)

    def detail(self) -> dict[str, Any]:  # (told at every tick a brain's run drives an input: kept short)
        return {"name": self.name, "value": self.value}


@dataclass(frozen=True)
class SetParam(Set):
    """A run-time parameter set (``module.param``)."""

    kind: ClassVar[str] = "param"


# -- the scene ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Make(Edit):
    """The objects simulated; ``others``: ``frozen`` or ``absent`` (`World.make`)."""

    kind: ClassVar[str] = "make"
    objects: tuple[str, ...]
    others: str = "frozen"  # (a recording from before ``others`` was recorded froze the others)

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.make(list(self.objects), others=self.others)


@dataclass(frozen=True)
class NoCollision(Edit):
    kind: ClassVar[str] = "no_collision"
    objects: tuple[str, ...]

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.no_collision(list(self.objects))


@dataclass(frozen=True)
class MakeJoint(Edit):
    """A joint between bodies ``a`` and ``b`` as they stand; ``axis`` and ``anchor`` in the world frame, SI."""

    kind: ClassVar[str] = "make_joint"
    a: str
    b: str
    joint: str | None = None
    joint_kind: str = "weld"
    axis: tuple[float, ...] | None = None
    anchor: tuple[float, ...] | None = None

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        return world.make_joint(self.a, self.b, self.joint, kind=self.joint_kind, axis=self.axis, anchor=self.anchor)

    def detail(self) -> dict[str, Any]:
        out: dict[str, Any] = {"a": self.a, "b": self.b, "joint": self.joint}
        if self.joint_kind != "weld" or self.axis is not None or self.anchor is not None:
            out["kind"] = self.joint_kind
            out.update({k: list(v) for k, v in (("axis", self.axis), ("anchor", self.anchor)) if v is not None})
        return out

    @classmethod
    def from_detail(cls, detail: dict[str, Any]) -> Edit:
        if isinstance(detail, dict) and "kind" in detail:
            detail = {("joint_kind" if k == "kind" else k): v for k, v in detail.items()}
        return super().from_detail(detail)


@dataclass(frozen=True)
class RemoveJoint(Edit):
    kind: ClassVar[str] = "remove_joint"
    joint: str

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.remove_joint(self.joint)


@dataclass(frozen=True)
class AddBody(Edit):
    """A body added while the world runs, as its spec."""

    kind: ClassVar[str] = "body_added"
    spec: BodySpec

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        return world.add_body(self.spec)

    def detail(self) -> dict[str, Any]:
        return {"body": self.spec.name, "spec": body_detail(self.spec)}

    @classmethod
    def needs(cls) -> tuple[str, ...]:
        return ("body", "spec")

    @classmethod
    def from_detail(cls, detail: dict[str, Any]) -> Edit:
        """A recorded body is plain values (a mesh's vertices and faces, not its file): no code runs."""
        try:
            return cls(body_from_detail(detail.get("spec") if isinstance(detail, dict) else detail))
        except BodySpecError as exc:
            raise EditFormatError(f"its spec: {exc}") from None


@dataclass(frozen=True)
class RemoveBody(Edit):
    """An object removed; ``disconnected``: the connections that went with its ports (as told)."""

    kind: ClassVar[str] = "body_removed"
    body: str
    disconnected: tuple[str, ...] = ()

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.remove_body(self.body)


@dataclass(frozen=True)
class SetMaterial(Edit):
    """A body's own friction, restitution and mass (None: the core's, the model's own)."""

    kind: ClassVar[str] = "material"
    body: str
    friction: float | None
    restitution: float | None
    mass: float | None = None

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.set_material(self.body, friction=self.friction, restitution=self.restitution, mass=self.mass)


@dataclass(frozen=True)
class Place(Edit):
    """A free body moved to a pose, at rest (``quat`` w-x-y-z; None keeps its orientation)."""

    kind: ClassVar[str] = "place"
    body: str
    pos: tuple[float, ...]
    quat: tuple[float, ...] | None = None

    def apply(self, world: World, make_module: ModuleMaker | None = None) -> Any:
        world.place(self.body, self.pos, self.quat)


EDITS: dict[str, type[Edit]] = {cls.kind: cls for cls in (
    AddModule, RemoveModule, Connect, Disconnect, DeclareLoop, Set, SetParam, Make, NoCollision, MakeJoint,
    RemoveJoint, AddBody, RemoveBody, SetMaterial, Place)}
"""Every kind of edit by its event's name."""


def edit_of(kind: str, detail: dict[str, Any]) -> Edit:
    """The record of a recorded edit (an event's ``kind`` and ``detail``); `EditFormatError` when it is
    no edit or its detail is damaged."""
    cls = EDITS.get(kind)
    if cls is None:
        raise EditFormatError(f"{kind!r} is no edit; edits: {', '.join(EDITS)}")
    return cls.from_detail(detail)
