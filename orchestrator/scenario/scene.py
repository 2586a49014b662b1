"""The ``scene:`` section of a scenario: primitives (engine-neutral) or a model file.

``- box: {name: aa, size: [0.1, 0.1, 0.1], mass: 50g, pos: [0, 0, 0.6], color: blue}``; shapes are
plane, box (full edge lengths), sphere ([radius]), capsule and cylinder ([radius, length]).
``joint:`` is ``free`` (the default for a top-level body), ``fixed``, or ``{hinge: {axis, anchor,
range, damping}}`` / ``{slide: {...}}`` (a hinge range is in degrees unless a unit says otherwise);
``parent:`` attaches a body to another. ``friction:`` and ``restitution:`` are the body's own
coefficients (the core's otherwise; `PhysicsCore.set_material` changes them at run time).
``euler: [rx, ry, rz]`` (degrees, applied x then y then z) may replace ``quat``.
``- grid: {of: {box: {...}}, count: [nx, ny], spacing: [dx, dy]}`` repeats a shape on a grid; the
copies are named ``<name>_<i>_<j>`` and placed at ``pos + (i*dx, j*dy, 0)``.
``- cable: {name: rope, from: [0, 0, 2], to: [0, 0, 0.5], radius: 5mm, mass: 100g, segments: 8,
stiffness: 2e4, bending: 1e-3, damping: 1ms, attach: [world, seat]}`` is a flexible rope (only some
cores simulate it; see `dynabrain.orchestrator.core.CableSpec`): ``stiffness`` is EA in N,
``bending`` EI in N*m^2, ``damping`` a time constant, ``attach`` what holds its start and end
(null: free, ``world``: pinned where it is, or a body's name).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..kernel.core import COLORS, FLEX_SHAPES, JOINT_KINDS, SHAPES, BodySpec, CableSpec, JointSpec, SceneSpec
from ..kernel.errors import DynabrainError, Problem, UnitError
from ..kernel.meshes import parse_mesh
from ..kernel.plugins import resolve_core
from ..kernel.specs import parse_color
from ..kernel.suggest import did_you_mean
from ..kernel.units import parse_quantity
from ..kernel.yamlsrc import Path, YamlSource
from . import limits
from .limits import bounded, short
from .modelfile import ModelFileError, count_bodies

_BODY_KEYS = ("name", "size", "pos", "quat", "euler", "mass", "color", "joint", "parent", "friction", "restitution",
              "mesh", "scale")
_JOINT_KEYS = ("name", "axis", "anchor", "range", "damping")
_SIZE_LEN = {"plane": (0, 2), "box": (3,), "sphere": (1,), "capsule": (2,), "cylinder": (2,), "mesh": (0,)}
_CABLE_KEYS = ("name", "from", "to", "radius", "mass", "segments", "stiffness", "bending", "damping", "attach",
               "color", "friction")
_ALL_SHAPES = (*SHAPES, *FLEX_SHAPES)


def parse_scene(data: Any, src: YamlSource, base_dir: str, engine: str) -> tuple[SceneSpec, list[Problem]]:
    """A SceneSpec and the problems found (every one, with its line)."""
    problems: list[Problem] = []
    if isinstance(data, dict):
        unknown = [k for k in data if k not in ("model", "options")]
        for key in unknown:
            problems.append(src.problem(("scene", key), f"unknown key {key!r} in scene; a scene is a list of "
                                        "primitives or {model: file, options: {...}}"
                                        + did_you_mean(key, ["model", "options"])))
        model = data.get("model")
        if not isinstance(model, str):
            problems.append(src.problem(("scene",), "scene.model must be a file path"))
            return SceneSpec(), problems
        path = model if os.path.isabs(model) else os.path.join(base_dir, model)
        if not os.path.exists(path):
            problems.append(src.problem(("scene", "model"), f"model file {model!r} not found (looked in {base_dir})"))
        else:
            try:  # within limits, before the engine reads it
                count_bodies(path)
            except ModelFileError as exc:
                problems.append(src.problem(("scene", "model"), f"{model}: {exc}"))
        return SceneSpec(model=path, options=_options(data.get("options"), src, engine, problems)), problems
    if data is not None and not isinstance(data, list):
        problems.append(src.problem(("scene",), f"a scene is a list of shapes or {{model: file}}, got {short(data)}"))
        return SceneSpec(), problems
    bodies: list[BodySpec] = []
    names: set[str] = set()
    for shape, fields, path in _items(data or [], src, problems):
        if shape not in _ALL_SHAPES:
            problems.append(src.problem(path, f"unknown shape {shape!r}" + did_you_mean(shape, _ALL_SHAPES)
                                        + f"; shapes: {', '.join(_ALL_SHAPES)}"))
            continue
        try:
            if shape in FLEX_SHAPES:
                body = _cable(shape, fields or {}, src, (*path, shape), problems)
            else:
                body = _body(shape, fields or {}, src, (*path, shape), problems, base_dir)
        except (DynabrainError, ValueError, TypeError, ArithmeticError) as exc:
            problems.append(src.problem((*path, shape), str(exc)))
            continue
        if body is None:
            continue
        if body.name in names:
            problems.append(src.problem((*path, shape, "name"), f"body name {body.name!r} is used twice"))
        names.add(body.name)
        bodies.append(body)
    for i, body in enumerate(bodies):
        if body.parent is not None and body.parent not in names:
            problems.append(Problem(f"unknown parent {body.parent!r}" + did_you_mean(body.parent, names),
                                    src.file, body.line, f"scene[{i}].parent"))
        for end in body.cable.attach if body.cable is not None else ():
            if end not in (None, "world") and (end not in names or end == body.name):
                problems.append(Problem(f"cable {body.name!r} is attached to {end!r}, which is not another body"
                                        + did_you_mean(end, names) + "; use a body's name, world or null",
                                        src.file, body.line, f"scene[{i}].attach"))
    return SceneSpec(bodies=tuple(bodies)), problems


def _options(data: Any, src: YamlSource, engine: str, problems: list[Problem]) -> dict[str, Any]:
    """``scene: {model: file, options: {...}}``: the engine's physics options, which override the model
    file's own (MuJoCo's ``<option>``: timestep, integrator, cone, solver, iterations ...). Each is checked
    by the core's ``option_problem`` when it has one; a bad one is reported with its line and left out.
    ``timestep`` takes a unit (``1ms``)."""
    if data is None:
        return {}
    if not isinstance(data, dict):
        problems.append(src.problem(("scene", "options"), f"options are a mapping of option: value, got {short(data)}"))
        return {}
    try:
        check = getattr(resolve_core(engine), "option_problem", None)
    except DynabrainError:
        check = None  # (an unknown core is reported at world.core)
    out: dict[str, Any] = {}
    for key, value in data.items():
        try:
            value = parse_quantity(value, "time") if key == "timestep" and isinstance(value, str) else value
        except (UnitError, ValueError) as exc:
            problems.append(src.problem(("scene", "options", key), f"option timestep: {exc}"))
            continue
        problem = check(key, value) if check is not None else None
        if problem:
            problems.append(src.problem(("scene", "options", key), problem))
            continue
        out[key] = value
    return out


def _items(data: list[Any], src: YamlSource, problems: list[Problem]):
    """(shape, fields, path) of each scene item, with grids expanded."""
    for i, item in enumerate(data):
        path: Path = ("scene", i)
        if not isinstance(item, dict) or len(item) != 1:
            problems.append(src.problem(path, "each scene item is one shape: `- box: {...}`"))
            continue
        shape, fields = next(iter(item.items()))
        if shape != "grid":
            yield shape, fields, path
            continue
        try:
            yield from _grid(fields, path)
        except (DynabrainError, ValueError, TypeError, KeyError, AttributeError, ArithmeticError) as exc:
            problems.append(src.problem((*path, "grid"), f"a grid is {{of: {{shape: {{...}}}}, count: [nx, ny], "
                                        f"spacing: [dx, dy]}}: {exc}"))


def _grid(fields: dict[str, Any], path: Path):
    (shape, base), = fields["of"].items()
    if not isinstance(base, dict):
        raise UnitError(f"{shape} needs a mapping of fields")
    count = fields["count"]
    if not isinstance(count, list) or len(count) != 2 or not all(_whole(c) and c >= 1 for c in count):
        raise UnitError(f"count is [nx, ny], two whole numbers from 1, got {short(count)}")
    nx, ny = count
    if nx * ny > limits.MAX_GRID:
        raise UnitError(f"{nx} x {ny} copies: a grid makes at most {limits.MAX_GRID} (MAX_GRID)")
    dx, dy = _vector(fields["spacing"], 2, "length")
    x0, y0, z0 = _vector(base.get("pos", [0, 0, 0]), 3, "length")
    for ix in range(nx):
        for iy in range(ny):
            copy = dict(base, name=f"{base.get('name', shape)}_{ix}_{iy}", pos=[x0 + ix * dx, y0 + iy * dy, z0])
            yield shape, copy, (*path, "grid", "of", shape)


def _field_reader(shape: str, f: dict[str, Any], keys: Sequence[str], src: YamlSource, path: Path,
                  problems: list[Problem], *, required: bool):
    """Check ``f``'s keys against ``keys`` and return ``field(key, parse, default)``, which parses one
    field, records a problem (and gives ``default``) when it is bad, and, with ``required``, when a
    field without a default is missing."""
    if not isinstance(f, dict):
        raise DynabrainError(f"{shape} needs a mapping of fields ({', '.join(keys)})")
    for key in f:
        if key not in keys:
            problems.append(src.problem((*path, key), f"unknown key {key!r}" + did_you_mean(key, keys)
                                        + f"; valid keys: {', '.join(keys)}"))

    def field(key: str, parse, default=None):
        if key not in f:
            if required and default is None:
                problems.append(src.problem(path, f"a {shape} needs {key!r}"))
            return default
        try:
            return parse(f[key])
        except (DynabrainError, ValueError, TypeError, ArithmeticError) as exc:
            problems.append(src.problem((*path, key), str(exc)))
            return default

    return field


def _body(shape: str, f: dict[str, Any], src: YamlSource, path: Path, problems: list[Problem],
          base_dir: str | None = None) -> BodySpec | None:
    """A rigid body; a mesh's file (``mesh: part.obj``) is relative to ``base_dir`` and read now."""
    before = len(problems)
    field = _field_reader(shape, f, _BODY_KEYS, src, path, problems, required=False)
    for key in ("mesh", "scale"):
        if key in f and shape != "mesh":
            problems.append(src.problem((*path, key), f"only a mesh takes {key!r} (this is a {shape})"))
    if shape == "mesh" and "mesh" not in f:
        problems.append(src.problem(path, "a mesh needs 'mesh': a file (.obj, .stl), {vertices, faces} or a "
                                    "list of vertices"))
    mesh = field("mesh", lambda v: parse_mesh(v, base_dir)) if shape == "mesh" else None
    scale = field("scale", lambda v: _scale(v)) if shape == "mesh" else None

    name = f.get("name", "floor" if shape == "plane" else None)
    if not _good_name(name):
        problems.append(src.problem((*path, "name") if "name" in f else path, _name_problem(shape, name)))
        name = "?"
    parent = f.get("parent")
    if parent is not None and not isinstance(parent, str):
        problems.append(src.problem((*path, "parent"), f"parent is a body's name, got {short(parent)}"))
    size = field("size", lambda v: _vector(v, None, "length"), ())
    if len(size) not in _SIZE_LEN[shape]:
        problems.append(src.problem((*path, "size"), f"a {shape} has size of length "
                                    f"{' or '.join(map(str, _SIZE_LEN[shape]))}, got {len(size)}"))
    if any(s <= 0 for s in size):
        problems.append(src.problem((*path, "size"), "sizes must be positive"))
    quat = field("quat", lambda v: _unit_quat(_vector(v, 4)), (1.0, 0.0, 0.0, 0.0))
    if "euler" in f:
        quat = field("euler", lambda v: _euler(_vector(v, 3, "angle", default_unit="deg")), quat)
    joint = field("joint", _joint)
    if shape == "plane" and joint not in (None,) and joint.kind != "fixed":
        problems.append(src.problem((*path, "joint"), "a plane is static; it takes no joint"))
    fields = dict(pos=field("pos", lambda v: _vector(v, 3, "length"), (0.0, 0.0, 0.0)), quat=quat,
                  mass=field("mass", _mass), color=field("color", _color, COLORS["grey"]), joint=joint,
                  parent=parent, friction=field("friction", _friction), line=src.line(path),
                  restitution=field("restitution", _restitution), mesh=mesh, scale=scale)
    if len(problems) != before:
        return None
    return BodySpec(name=name, shape=shape, size=tuple(size), **fields)


def _scale(value: Any) -> tuple[float, float, float]:
    out = (parse_quantity(value, None),) * 3 if isinstance(value, (int, float, str)) else _vector(value, 3)
    if not all(x > 0 for x in out):
        raise UnitError(f"a scale is a positive number or three, got {short(value)}")
    return out


def parse_body(item: Any, src: YamlSource, path: Path, base_dir: str | None = None
               ) -> tuple[BodySpec | None, list[Problem]]:
    """One rigid body written as a scene item (``{box: {name: ..., size: ...}}``) at ``path`` (a scenario
    event's ``add_body``), with the problems found (each with its line); a mesh file is relative to
    ``base_dir``."""
    problems: list[Problem] = []
    if not isinstance(item, dict) or len(item) != 1:
        return None, [src.problem(path, "a body is one shape: {box: {name: ..., size: [...], ...}}")]
    (shape, fields), = item.items()
    if shape not in SHAPES or shape == "plane":
        shapes = [s for s in SHAPES if s != "plane"]
        return None, [src.problem(path, f"a body added at run time is one of {', '.join(shapes)}, got {shape!r}"
                                  + did_you_mean(str(shape), shapes))]
    try:
        body = _body(shape, fields or {}, src, (*path, shape), problems, base_dir)
    except (DynabrainError, ValueError, TypeError, ArithmeticError) as exc:
        return None, [src.problem((*path, shape), str(exc))]
    if body is not None and body.parent is not None:
        problems.append(src.problem((*path, shape, "parent"), "a body added at run time is top-level (join it to "
                                    "another with make_joint)"))
        body = None
    return body, problems


def _cable(shape: str, f: dict[str, Any], src: YamlSource, path: Path, problems: list[Problem]) -> BodySpec | None:
    """A ``cable`` item: a flexible rope from ``from`` to ``to`` (see `CableSpec`)."""
    before = len(problems)
    field = _field_reader(shape, f, _CABLE_KEYS, src, path, problems, required=True)

    name = f.get("name")
    if not _good_name(name):
        problems.append(src.problem((*path, "name") if "name" in f else path, _name_problem(shape, name)))
    start = field("from", lambda v: _vector(v, 3, "length"))
    end = field("to", lambda v: _vector(v, 3, "length"))
    if start is not None and end is not None and start == end:
        problems.append(src.problem((*path, "to"), "a cable's ends must differ"))
    cable = CableSpec(
        end=end or (0.0, 0.0, 0.0),
        segments=field("segments", _segments, 8),
        axial_stiffness=field("stiffness", _above_zero("force", "stiffness", limits.MAX_MAGNITUDE), 1.0e4),
        bending_stiffness=field("bending", _above_zero(None, "bending", limits.MAX_MAGNITUDE), 1.0e-3),
        damping=field("damping", lambda v: _quantity(v, "time", "damping", 0.0, limits.MAX_DURATION_S), 0.0),
        attach=field("attach", _attach, (None, None)),
    )
    body = BodySpec(
        name=name if isinstance(name, str) else "?", shape=shape,
        size=(field("radius", _above_zero("length", "radius", limits.MAX_LENGTH_M), 0.005),),
        pos=start or (0.0, 0.0, 0.0),
        mass=field("mass", _mass, 0.0) or None,
        color=field("color", _color, COLORS["brown"]), friction=field("friction", _friction, 0.0) or None,
        line=src.line(path), cable=cable,
    )
    return body if len(problems) == before else None


def _segments(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 500:
        raise UnitError(f"segments is a whole number from 1 to 500, got {value!r}")
    return value


def _attach(value: Any) -> tuple[str | None, str | None]:
    if not isinstance(value, list) or len(value) != 2 or not all(v is None or isinstance(v, str) for v in value):
        raise UnitError("attach is [start, end], each a body's name, world or null")
    return (value[0], value[1])


def _whole(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _good_name(name: Any) -> bool:
    return isinstance(name, str) and bool(name.strip()) and len(name) <= limits.MAX_NAME


def _name_problem(shape: str, name: Any) -> str:
    if isinstance(name, str) and len(name) > limits.MAX_NAME:
        return f"a name is at most {limits.MAX_NAME} characters (MAX_NAME), got {len(name)}"
    return f"a {shape} needs a name (a string), got {short(name)}"


def _quantity(value: Any, dimension: str | None, what: str, low: float, high: float, *, above: bool = False) -> float:
    """``value`` in SI units, finite, within [low, high] (above ``low`` with ``above``)."""
    try:
        x = parse_quantity(value, dimension)
    except OverflowError:
        raise UnitError(f"{what} {short(value)} is too large") from None
    bounded(x, what, None, high)
    if x < low or (above and x == low):
        raise UnitError(f"{what} must be {'above' if above else 'at least'} {low:g}, got {x:g}")
    return x


def _above_zero(dimension: str | None, what: str, high: float):
    """A parser of a quantity above 0 and at most ``high``."""
    return lambda value: _quantity(value, dimension, what, 0.0, high, above=True)


_friction = _above_zero(None, "friction", limits.MAX_FRICTION)


def _restitution(value: Any) -> float:
    return _quantity(value, None, "restitution", 0.0, 1.0)
_mass = _above_zero("mass", "mass", limits.MAX_MASS_KG)


def _vector(value: Any, n: int | None, dimension: str | None = None, default_unit: str | None = None) -> tuple:
    """A list of ``n`` quantities in SI units, each finite and within `MAX_LENGTH_M` (lengths) or
    `MAX_MAGNITUDE` (anything else)."""
    if not isinstance(value, (list, tuple)):
        raise UnitError(f"expected a list of {n or 'some'} numbers, got {short(value)}")
    if n is not None and len(value) != n:
        raise UnitError(f"expected {n} numbers, got {len(value)}")
    limit = limits.MAX_LENGTH_M if dimension == "length" else limits.MAX_MAGNITUDE
    out = []
    for v in value:
        if default_unit and not isinstance(v, (str, bool)):
            v = f"{v}{default_unit}"
        out.append(_quantity(v, dimension, dimension or "a number", -limit, limit))
    return tuple(out)


def parse_vector(value: Any, n: int | None, dimension: str | None = None) -> tuple:
    """A list of ``n`` quantities in SI units, each finite and within the scenario's limits (an event's
    axis or anchor)."""
    return _vector(value, n, dimension)


def parse_pose(value: Any) -> tuple[tuple, tuple | None]:
    """A pose as a scenario writes it (``[x, y, z]`` or ``{pos: [x, y, z], quat: [w, x, y, z]}``), as
    (pos, unit quat or None), in SI units; a `UnitError` says what is wrong."""
    if isinstance(value, dict):
        unknown = [k for k in value if k not in ("pos", "quat")]
        if unknown or "pos" not in value:
            raise UnitError(f"a pose is [x, y, z] or {{pos: [x, y, z], quat: [w, x, y, z]}}, got {short(value)}")
        quat = value.get("quat")
        return _vector(value["pos"], 3, "length"), None if quat is None else _unit_quat(_vector(quat, 4))
    return _vector(value, 3, "length"), None


def _unit_quat(q: tuple) -> tuple:
    norm = math.sqrt(sum(x * x for x in q))
    if norm == 0:
        raise UnitError("a quaternion cannot be zero")
    return tuple(x / norm for x in q)


def _euler(angles: tuple) -> tuple:
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for axis, angle in enumerate(angles):
        r = np.zeros(4)
        r[0] = math.cos(angle / 2)
        r[1 + axis] = math.sin(angle / 2)
        q = _qmul(r, q)
    return tuple(float(x) for x in q)


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _color(value: Any) -> tuple:
    """A colour name or [r, g, b(, a)] (the kernel's rule, which `BodySpec` applies to the Python API too)."""
    return parse_color(value if isinstance(value, str) else _vector(value, None))


def _joint(value: Any) -> JointSpec:
    if isinstance(value, str):
        if value not in JOINT_KINDS:
            raise UnitError(f"unknown joint {value!r}" + did_you_mean(value, JOINT_KINDS)
                            + f"; joints: {', '.join(JOINT_KINDS)}")
        return JointSpec(kind=value)
    if not isinstance(value, dict) or len(value) != 1:
        raise UnitError("a joint is free, fixed, or {hinge: {...}} / {slide: {...}}")
    kind, fields = next(iter(value.items()))
    if kind not in ("hinge", "slide"):
        raise UnitError(f"unknown joint kind {kind!r}" + did_you_mean(kind, ("hinge", "slide")))
    fields = fields or {}
    if not isinstance(fields, dict):
        raise UnitError(f"a {kind} joint takes a mapping of fields ({', '.join(_JOINT_KEYS)})")
    for key in fields:
        if key not in _JOINT_KEYS:
            raise UnitError(f"unknown joint key {key!r}" + did_you_mean(key, _JOINT_KEYS))
    rng = fields.get("range")
    dim = "angle" if kind == "hinge" else "length"
    name = fields.get("name")
    if name is not None and not _good_name(name):
        raise UnitError(_name_problem(f"{kind} joint", name))
    return JointSpec(
        kind=kind, name=name,
        axis=_axis(fields.get("axis", [0, 0, 1])),
        anchor=_vector(fields.get("anchor", [0, 0, 0]), 3, "length"),
        range=None if rng is None else _vector(rng, 2, dim, default_unit="deg" if kind == "hinge" else None),
        damping=_quantity(fields.get("damping", 0.0), None, "damping", 0.0, limits.MAX_MAGNITUDE),
    )


def _axis(value: Any) -> tuple:
    v = np.array(_vector(value, 3))
    n = np.linalg.norm(v)
    if n == 0:
        raise UnitError("a joint axis cannot be zero")
    return tuple(float(x) for x in v / n)
