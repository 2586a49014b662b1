"""Scene specs: the bodies, joints and cables a scene is made of, the structural edits a core keeps,
and the rules that turn a brain's or a scenario's values into SI numbers.

A `BodySpec` takes its values in SI numbers or as a scenario file writes them (``"100mm"``, ``"50g"``,
a colour name such as ``"blue"``): `normalise` turns them into SI floats and a colour into RGBA, and
refuses what no core could build, naming the body and the field (`BodySpecError`). The scenario
layer parses its YAML bodies with the same unit and colour rules (`parse_color`, `units`).

Specs are plain, immutable values: the physics cores (`kernel.core`) build from them, history and
logs keep them, and nothing here knows a core.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from .errors import DynabrainError, UnitError
from .meshes import Mesh, parse_mesh
from .portable import state_type
from .suggest import did_you_mean
from .units import parse_quantity

SHAPES = ("plane", "box", "sphere", "capsule", "cylinder", "mesh")
FLEX_SHAPES = ("cable",)
"""Shapes of flexible bodies (not every core has them; see `CableSpec`)."""
JOINT_KINDS = ("free", "hinge", "slide", "fixed")

COLORS: dict[str, tuple[float, float, float, float]] = {
    "red": (0.85, 0.15, 0.15, 1.0),
    "green": (0.2, 0.7, 0.25, 1.0),
    "blue": (0.15, 0.3, 0.85, 1.0),
    "yellow": (0.95, 0.85, 0.1, 1.0),
    "orange": (0.95, 0.55, 0.1, 1.0),
    "purple": (0.55, 0.25, 0.75, 1.0),
    "cyan": (0.1, 0.75, 0.85, 1.0),
    "magenta": (0.85, 0.2, 0.7, 1.0),
    "white": (0.95, 0.95, 0.95, 1.0),
    "grey": (0.5, 0.5, 0.5, 1.0),
    "gray": (0.5, 0.5, 0.5, 1.0),
    "black": (0.08, 0.08, 0.08, 1.0),
    "brown": (0.5, 0.3, 0.15, 1.0),
}



@dataclass(frozen=True)
class JointSpec:
    """How a body is attached to its parent (the world when it has none).

    ``axis`` is in the body frame; ``anchor`` is the joint's position in the body frame.
    ``range`` limits a hinge (rad) or slide (m).
    """

    kind: str = "free"
    name: str | None = None
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    anchor: tuple[float, float, float] = (0.0, 0.0, 0.0)
    range: tuple[float, float] | None = None
    damping: float = 0.0


@dataclass(frozen=True)
class CableSpec:
    """What a ``cable`` body has beyond a `BodySpec`: a rope, straight at t=0 from the body's ``pos``
    (world frame) to ``end``, of ``segments`` beam elements.

    ``axial_stiffness`` is EA (N: the force that would double its length), ``bending_stiffness`` EI
    (N*m^2), ``damping`` a time constant (s): the axial and bending damping are ``damping`` times the
    stiffnesses. ``attach`` says what holds each end (start, end): None for a free end, ``"world"``
    to pin it where it is, or a body's name to pin it to that body at the point where it is at t=0.
    The body's ``size`` is ``(radius,)`` and its ``mass`` the whole cable's.
    """

    end: tuple[float, float, float]
    segments: int = 8
    axial_stiffness: float = 1.0e4
    bending_stiffness: float = 1.0e-3
    damping: float = 0.0
    attach: tuple[str | None, str | None] = (None, None)


@dataclass(frozen=True)
class BodySpec:
    """One primitive body of a scene.

    ``size`` by shape: box: full edge lengths (x, y, z); sphere: (radius,); capsule and cylinder:
    (radius, length along the body z axis); plane: (half-x, half-y) or () for infinite; cable:
    (radius,), with the rest in ``cable``; mesh: () (its ``mesh`` and ``scale`` say).
    A ``mesh`` body's ``mesh`` is a file (``.obj``, ``.stl``; read when the spec is made), ``{vertices,
    faces}`` or a list of vertices, in the body frame, times ``scale`` (a number or three); it becomes a
    `kernel.meshes.Mesh`. Both cores simulate it as its convex hull (contacts, mass and inertia; MuJoCo
    collides a mesh as its hull); its body frame is the mesh's own (not its centre of mass).
    ``pos`` is in the parent's frame (the world's when ``parent`` is None); ``quat`` is w-x-y-z.
    A plane is always static; a top-level body without ``joint`` is free.

    Values may be written as a scenario writes them: lengths and masses with units (``"100mm"``,
    ``"50g"``), a colour by name (``"blue"``) or RGB(A), a joint by kind (``"hinge"``); they become SI
    numbers when the spec is made, and a value no core can take raises `BodySpecError` naming the body
    and the field (`kernel.bodies.normalise`). ``friction`` and ``restitution`` are the body's own
    coefficients (None: the core's); `PhysicsCore.set_material` changes them at run time.
    """

    name: str
    shape: str
    size: tuple[float, ...] = ()
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    mass: float | None = None
    color: tuple[float, float, float, float] = COLORS["grey"]
    joint: JointSpec | None = None
    parent: str | None = None
    friction: float | None = None
    line: int | None = None
    """Line in the scenario file where the body is written (for errors)."""
    cable: CableSpec | None = None
    """The rope of a ``cable`` body (shape in `FLEX_SHAPES`); None for rigid shapes."""
    restitution: float | None = None
    """The body's own coefficient of restitution (0..1); None: the core's ``restitution``."""
    mesh: Any = None
    """The triangle mesh of a ``mesh`` body (a `kernel.meshes.Mesh` once made); None for other shapes."""
    scale: tuple[float, float, float] | None = None
    """The scale of a ``mesh`` body's vertices per axis ((1, 1, 1) once made); None for other shapes."""

    def __post_init__(self) -> None:
        for key, value in normalise(self).items():  # units and colour names as a scenario writes them
            object.__setattr__(self, key, value)


@dataclass(frozen=True)
class SceneSpec:
    """A scene: primitives, or an engine model file (``model``), plus options."""

    bodies: tuple[BodySpec, ...] = ()
    model: str | None = None
    """Path of an engine model file (MJCF for MuJoCo), resolved against the scenario's folder."""
    options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class BodyInfo:
    """What a core tells about one body (for viewers, logs and expectation expressions)."""

    name: str
    free: bool
    parent: str | None
    geoms: tuple[dict, ...] = ()


@state_type
class Weld(NamedTuple):
    """A joint made at run time (`PhysicsCore.make_joint`) between bodies ``a`` and ``b`` as they stood
    when it was made: a weld holds them rigidly, a hinge, slider or ball lets them turn or slide."""

    name: str
    """The joint's name (unique among the scene's joints and the other welds)."""
    a: str
    b: str
    data: tuple
    """What the engine needs to make the joint again: for a weld the relative pose, in the engine's
    terms; for the other kinds the joint's frame in each body (`kernel.bodies.JointFrames`)."""
    kind: str = "weld"
    """weld, hinge, slider or ball (`kernel.bodies.MADE_JOINT_KINDS`)."""


@state_type
class Material(NamedTuple):
    """A body's own contact coefficients and mass, set at run time (`PhysicsCore.set_material`); None:
    the core's parameter (for the mass: the model's own)."""

    body: str
    friction: float | None
    restitution: float | None
    mass: float | None = None
    """kg; the body's inertia scales with it (the same shape, denser or lighter)."""


@state_type
class Edits(NamedTuple):
    """The structural edits of an `EditedCore`, as one immutable, hashable value (part of its state:
    history keeps it, a restore compares it, a core caches what it compiled for it)."""

    frozen: tuple = ()
    """One engine-made entry per frozen object, a NamedTuple whose first field, ``object``, is the
    object's name (the rest: where its bodies and joints stood when it froze)."""
    welds: tuple[Weld, ...] = ()
    """The joints made at run time, in the order they were made."""
    groups: tuple[tuple[str, ...], ...] = ()
    """The objects of each `no_collision`, sorted, in the order the calls came."""
    added: tuple[BodySpec, ...] = ()
    """Bodies added at run time (`PhysicsCore.add_body`), in the order they came, each as it was
    added (its ``pos`` and ``quat`` where it appeared)."""
    removed: tuple[str, ...] = ()
    """Objects of the scene as written that `PhysicsCore.remove_body` took out (a body added at run
    time and removed again simply leaves ``added``)."""
    materials: tuple[Material, ...] = ()
    """The bodies whose friction or restitution was set at run time (`PhysicsCore.set_material`),
    sorted by body: their own coefficients from then on."""
    absent: tuple[str, ...] = ()
    """The frozen objects that are out of the simulation (`PhysicsCore.make` with ``others="absent"``), in
    object order: no geometry, no contacts, nothing computed; their entries in ``frozen`` say where they
    stood when they left (their outputs hold there, and they come back there, at rest)."""

    def scene_key(self) -> tuple:
        """What decides the core's ports: the bodies added and removed."""
        return (self.added, self.removed)

    def structural(self) -> Edits:
        """These edits without the materials (which an engine applies without rebuilding)."""
        return self._replace(materials=()) if self.materials else self


def scene_bodies(scene: SceneSpec, scene_key: tuple) -> tuple[BodySpec, ...]:
    """The primitives of ``scene`` once the bodies of ``scene_key`` (`Edits.scene_key`: added, removed)
    were added and removed: the scene's, less the removed objects and what hangs on them, then the
    added ones."""
    added, removed = scene_key
    kept = scene.bodies
    if removed:
        parent = {b.name: b.parent for b in kept}

        def gone(name: str | None) -> bool:
            while name is not None:
                if name in removed:
                    return True
                name = parent.get(name)
            return False

        kept = tuple(b for b in kept if not gone(b.name))
    return (*kept, *added)


KEEP: Any = type("Keep", (), {"__repr__": lambda self: "KEEP"})()
"""What `PhysicsCore.set_material` takes for a coefficient it should leave as it is."""

MAKE_OTHERS = ("frozen", "absent")
"""What `PhysicsCore.make` does with the objects it does not select: ``frozen`` (the default) keeps each where
it stands as a static obstacle (drawn, collided with); ``absent`` takes them out of the simulation."""

NO_EDITS = Edits()
"""The structure of a scene as it was written: nothing frozen, no weld, no collision filter."""


class BodySpecError(DynabrainError, ValueError):
    """A body whose values no core can build; ``field`` names the field (``size``, ``color`` ...)."""

    def __init__(self, body: Any, field: str, message: str, call: str | None = None):
        self.body, self.field, self.detail = body, field, message
        super().__init__((f"{call}(): " if call else "") + f"body {body!r}, field {field}: {message}")


def parse_color(value: Any) -> tuple[float, float, float, float]:
    """A colour as a name of `COLORS` or ``[r, g, b(, a)]`` in 0..1, as RGBA floats."""
    if isinstance(value, str):
        if value not in COLORS:
            raise UnitError(f"unknown colour {value!r}" + did_you_mean(value, COLORS)
                            + f"; colours: {', '.join(COLORS)}")
        return COLORS[value]
    try:
        rgba = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        raise UnitError(f"a colour is a name or [r, g, b(, a)] in 0..1, got {value!r}") from None
    if len(rgba) not in (3, 4) or not all(0 <= c <= 1 for c in rgba):
        raise UnitError(f"a colour is a name or [r, g, b(, a)] in 0..1, got {value!r}")
    return rgba if len(rgba) == 4 else (*rgba, 1.0)


def quantities(value: Any, n: int | None, dimension: str | None) -> tuple[float, ...]:
    """A list of ``n`` (any number with None) finite quantities in SI (numbers, or strings with a unit
    of ``dimension``)."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (Sequence, np.ndarray)):
        raise UnitError(f"expected a list of {n or 'some'} numbers, got {value!r}")
    if n is not None and len(value) != n:
        raise UnitError(f"expected {n} numbers, got {len(value)}")
    out = tuple(_quantity(v, dimension) for v in value)
    return out


def _quantity(value: Any, dimension: str | None) -> float:
    if type(value) is float and math.isfinite(value):  # the common case: already SI
        return value
    if isinstance(value, np.generic):
        value = value.item()
    return parse_quantity(value, dimension)


def normalise(spec: BodySpec) -> dict[str, Any]:
    """The fields of ``spec`` that change once in SI units (only those that differ); a `BodySpecError`
    names the body and the first field that no core can take."""
    name = spec.name
    if not isinstance(name, str) or not name.strip():
        raise BodySpecError(name, "name", f"a body needs a name (a non-empty string), got {name!r}")
    if not isinstance(spec.shape, str):
        raise BodySpecError(name, "shape", f"a shape is a name ({', '.join((*SHAPES, *FLEX_SHAPES))}), "
                            f"got {spec.shape!r}")
    out: dict[str, Any] = {}
    for key, n, dim in (("size", None, "length"), ("pos", 3, "length"), ("quat", 4, None)):
        value = getattr(spec, key)
        try:
            parsed = quantities(value, n, dim)
        except (UnitError, TypeError, ValueError, OverflowError) as exc:
            raise BodySpecError(name, key, str(exc)) from None
        if key == "size" and any(s <= 0 for s in parsed):
            raise BodySpecError(name, key, f"sizes must be positive, got {value!r}")
        if key == "quat" and not any(parsed):
            raise BodySpecError(name, key, "a quaternion cannot be zero")
        if parsed != value:
            out[key] = parsed
    for key, dim, low, high in (("mass", "mass", 0.0, None), ("friction", None, 0.0, None),
                                ("restitution", None, 0.0, 1.0)):
        value = getattr(spec, key)
        if value is None:
            continue
        try:
            x = _quantity(value, dim)
        except (UnitError, TypeError, ValueError, OverflowError) as exc:
            raise BodySpecError(name, key, str(exc)) from None
        if x < low or (key == "mass" and x == 0) or (high is not None and x > high):
            what = "above 0" if key == "mass" else (f"from {low:g} to {high:g}" if high is not None else "from 0")
            raise BodySpecError(name, key, f"{key} must be {what}, got {value!r}")
        if x is not value:
            out[key] = x
    if not (isinstance(spec.color, tuple) and len(spec.color) == 4 and all(type(c) is float for c in spec.color)):
        try:
            out["color"] = parse_color(spec.color)
        except UnitError as exc:
            raise BodySpecError(name, "color", str(exc)) from None
    joint = spec.joint
    if isinstance(joint, str):
        out["joint"] = JointSpec(kind=joint)
    elif joint is not None and not isinstance(joint, JointSpec):
        raise BodySpecError(name, "joint", f"a joint is a JointSpec or a kind (free, fixed, hinge, slide), "
                            f"got {joint!r}")
    if spec.parent is not None and not isinstance(spec.parent, str):
        raise BodySpecError(name, "parent", f"parent is a body's name, got {spec.parent!r}")
    out.update(_mesh_fields(spec))
    return out


def _mesh_fields(spec: BodySpec) -> dict[str, Any]:
    """``mesh`` and ``scale`` made (a mesh body), or refused (any other shape)."""
    name = spec.name
    if spec.shape != "mesh":
        for key in ("mesh", "scale"):
            if getattr(spec, key) is not None:
                raise BodySpecError(name, key, f"only a mesh body takes a {key} (this is a {spec.shape})")
        return {}
    out: dict[str, Any] = {}
    if spec.mesh is None:
        raise BodySpecError(name, "mesh", "a mesh body needs mesh: a file (.obj, .stl), {vertices, faces} or a "
                            "list of vertices")
    if not isinstance(spec.mesh, Mesh):
        try:
            out["mesh"] = parse_mesh(spec.mesh)
        except (UnitError, TypeError, ValueError, OverflowError) as exc:
            raise BodySpecError(name, "mesh", str(exc)) from None
    if spec.size:
        raise BodySpecError(name, "size", f"a mesh takes its size from its vertices and scale, got size {spec.size!r}")
    scale = spec.scale
    if not (isinstance(scale, tuple) and len(scale) == 3 and all(type(x) is float and x > 0 for x in scale)):
        try:
            value = (1.0, 1.0, 1.0) if scale is None else (
                (_quantity(scale, None),) * 3 if isinstance(scale, (int, float, str)) else quantities(scale, 3, None))
        except (UnitError, TypeError, ValueError, OverflowError) as exc:
            raise BodySpecError(name, "scale", f"{exc} (a scale is a number or three)") from None
        if not all(x > 0 for x in value):
            raise BodySpecError(name, "scale", f"scales must be positive, got {scale!r}")
        out["scale"] = value
    return out


def body_from_detail(detail: dict[str, Any]) -> BodySpec:
    """The `BodySpec` of an event's detail (`World` records a body it adds as plain values: a log's
    ``body_added``): plain values only, so nothing recorded runs code."""
    if not isinstance(detail, dict):
        raise BodySpecError(None, "spec", f"a recorded body is a mapping of its fields, got {type(detail).__name__}")
    fields = dict(detail)
    if fields.get("mesh") is not None and not isinstance(fields["mesh"], dict):
        raise BodySpecError(fields.get("name"), "mesh", "a recorded mesh is its vertices and faces, not a file")
    for key, cls in (("joint", JointSpec), ("cable", CableSpec)):
        value = fields.get(key)
        if isinstance(value, dict):
            try:
                fields[key] = cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in value.items()})
            except TypeError as exc:
                raise BodySpecError(fields.get("name"), key, str(exc)) from None
    try:
        return BodySpec(**fields)
    except TypeError as exc:
        raise BodySpecError(fields.get("name"), "spec", str(exc)) from None


def body_detail(spec: BodySpec) -> dict[str, Any]:
    """A body's spec as plain values in SI (`body_from_detail` takes them back: an event's detail, a log)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(spec):
        value = getattr(spec, f.name)
        if f.name == "line" or value is None:
            continue
        out[f.name] = dataclasses.asdict(value) if dataclasses.is_dataclass(value) else (
            value.plain() if f.name == "mesh" else list(value) if isinstance(value, tuple) else value)
    return out
