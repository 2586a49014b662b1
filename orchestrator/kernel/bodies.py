"""Bodies as a brain writes them, and the frames of joints made at run time.

A `BodySpec` takes its values in SI numbers or as a scenario file writes them (``"100mm"``, ``"50g"``,
a colour name such as ``"blue"``): `normalise` turns them into SI floats and a colour into RGBA, and
refuses what no core could build, naming the body and the field (`BodySpecError`). The scenario
layer parses its YAML bodies with the same unit and colour rules (`parse_color`, `units`).

A joint made at run time (`PhysicsCore.make_joint` with a ``kind`` other than ``weld``) is kept as
`JointFrames`: the joint's frame in each of the two bodies, as they stood when it was made. The
frame's z axis is the joint's axis (a hinge turns about it, a slider slides along it) and its origin
the anchor. Both cores build their joint from these values, so they are engine-neutral.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from .errors import DynabrainError, UnitError
from .portable import state_type
from .suggest import did_you_mean
from .units import parse_quantity

if TYPE_CHECKING:
    from .core import BodySpec

MADE_JOINT_KINDS = ("weld", "hinge", "slider", "ball")
"""Kinds of joint `PhysicsCore.make_joint` makes: weld (rigid), hinge (turns about an axis), slider
(slides along an axis, orientation kept) and ball (turns freely about an anchor)."""
_ALIASES = {"slide": "slider", "fixed": "weld", "revolute": "hinge", "prismatic": "slider", "spherical": "ball"}


class BodySpecError(DynabrainError, ValueError):
    """A body whose values no core can build; ``field`` names the field (``size``, ``color`` ...)."""

    def __init__(self, body: Any, field: str, message: str, call: str | None = None):
        self.body, self.field, self.detail = body, field, message
        super().__init__((f"{call}(): " if call else "") + f"body {body!r}, field {field}: {message}")


def parse_color(value: Any) -> tuple[float, float, float, float]:
    """A colour as a name of `COLORS` or ``[r, g, b(, a)]`` in 0..1, as RGBA floats."""
    from .core import COLORS

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
    from .core import FLEX_SHAPES, SHAPES, JointSpec

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
    from .meshes import Mesh, parse_mesh

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
    from .core import BodySpec, CableSpec, JointSpec

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


def joint_kind(kind: Any) -> str:
    """The kind of a joint made at run time, by its name (or a common alias: slide, revolute, ...)."""
    kind = _ALIASES.get(kind, kind) if isinstance(kind, str) else kind
    if kind not in MADE_JOINT_KINDS:
        raise UnitError(f"unknown joint kind {kind!r}" + did_you_mean(str(kind), MADE_JOINT_KINDS)
                        + f"; kinds: {', '.join(MADE_JOINT_KINDS)}")
    return kind


# -- joint frames ---------------------------------------------------------------------------------------
@state_type
class JointFrames(NamedTuple):
    """The frame of a joint made at run time in each of its two bodies (`Weld.data` of a hinge,
    slider or ball): origin at the anchor, z along the axis, as they stood when it was made."""

    pos_a: tuple[float, float, float]
    """The anchor in body a's frame."""
    quat_a: tuple[float, float, float, float]
    """The joint frame's orientation in body a's frame (w, x, y, z)."""
    pos_b: tuple[float, float, float]
    quat_b: tuple[float, float, float, float]


def joint_frames(pose_a: tuple[np.ndarray, np.ndarray], pose_b: tuple[np.ndarray, np.ndarray],
                 anchor: Sequence[float], axis: Sequence[float]) -> JointFrames:
    """The frames of a joint at world ``anchor`` about (or along) world ``axis`` between bodies at
    world poses ``pose_a`` and ``pose_b`` (position, quaternion w-x-y-z)."""
    q_joint = quat_z_to(np.asarray(axis, dtype=float))
    out = []
    for pos, quat in (pose_a, pose_b):
        inv = qconj(np.asarray(quat, dtype=float))
        out.append(tuple(map(float, rotate(inv, np.asarray(anchor, dtype=float) - pos))))
        out.append(tuple(map(float, qnormal(qmul(inv, q_joint)))))
    return JointFrames(*out)


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def qconj(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]]) / float(np.dot(q, q))


def qnormal(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q)


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v`` rotated by the unit quaternion ``q``."""
    w, u = q[0], np.asarray(q[1:])
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_z_to(axis: np.ndarray) -> np.ndarray:
    """A unit quaternion that turns the z axis onto ``axis`` (not zero)."""
    a = axis / np.linalg.norm(axis)
    c = float(a[2])
    if c < -1.0 + 1e-12:
        return np.array([0.0, 1.0, 0.0, 0.0])
    v = np.array([-a[1], a[0], 0.0])  # z x a
    return qnormal(np.array([1.0 + c, *v]))
