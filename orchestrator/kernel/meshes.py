"""Triangle meshes of ``mesh`` bodies: reading them (Wavefront ``.obj``, ``.stl`` ASCII or binary, in
plain numpy), their convex hull (Qhull, through SciPy), and the mass properties of a closed mesh.

A `Mesh` is what a `BodySpec` keeps: the vertices (in the body frame, before the body's ``scale``) and
triangles (indices into them; empty when only vertices were given). A file is read once, when the spec
is made: the spec holds the numbers, not the path, so history, forks, exported states and logs need no
file, and a file changed later changes nothing already made.

Both cores treat a mesh body as its convex hull, for contacts (MuJoCo collides a mesh as its hull) and
for its mass and inertia (uniform density: 1000 kg/m^3 without a ``mass``). Its triangles, when given,
are what MuJoCo draws.
"""

from __future__ import annotations

import functools
import math
import os
import struct
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from .errors import UnitError
from .portable import state_type

MAX_VERTICES = 20_000
"""Most vertices of a mesh body (a log and a bridge message carry them)."""
MAX_FILE_BYTES = 64 * 2**20
"""Largest mesh file read."""
MESH_SUFFIXES = (".obj", ".stl")


@state_type
class Mesh(NamedTuple):
    """The vertices ((x, y, z), ...) and triangles ((i, j, k), ...; may be empty) of a mesh body."""

    vertices: tuple[tuple[float, float, float], ...]
    faces: tuple[tuple[int, int, int], ...] = ()

    def plain(self) -> dict[str, Any]:
        """As plain lists (an event's detail; `parse_mesh` takes it back)."""
        out: dict[str, Any] = {"vertices": [list(v) for v in self.vertices]}
        if self.faces:
            out["faces"] = [list(f) for f in self.faces]
        return out


def parse_mesh(value: Any, base_dir: str | None = None) -> Mesh:
    """A `Mesh` from a file path (``.obj`` or ``.stl``, relative to ``base_dir``), ``{vertices, faces}``
    (faces optional) or a list of vertices; `UnitError` says what is wrong (the caller names the field)."""
    if isinstance(value, Mesh):
        return value
    if isinstance(value, (str, os.PathLike)):
        return read_mesh(value if base_dir is None else os.path.join(base_dir, os.fspath(value)))
    if isinstance(value, Mapping):
        unknown = sorted(set(value) - {"vertices", "faces"})
        if unknown or "vertices" not in value:
            raise UnitError("an inline mesh is {vertices: [[x, y, z], ...], faces: [[i, j, k], ...]} (faces "
                            f"optional), got the keys {sorted(value)}")
        return make_mesh(value["vertices"], value.get("faces") or ())
    if isinstance(value, (Sequence, np.ndarray)) and not isinstance(value, bytes):
        return make_mesh(value, ())
    raise UnitError("a mesh is a file path (.obj, .stl), {vertices, faces} or a list of vertices, "
                    f"got {type(value).__name__}")


def make_mesh(vertices: Any, faces: Any) -> Mesh:
    """A checked `Mesh`: 4 to `MAX_VERTICES` finite vertices that span a volume, triangles that index them."""
    try:
        v = np.asarray(vertices, dtype=float)
    except (TypeError, ValueError):
        raise UnitError("mesh vertices are a list of [x, y, z] numbers") from None
    if v.ndim != 2 or v.shape[1] != 3:
        raise UnitError(f"mesh vertices are a list of [x, y, z] numbers, got an array of shape {v.shape}")
    if not 4 <= len(v) <= MAX_VERTICES:
        raise UnitError(f"a mesh has 4 to {MAX_VERTICES} vertices, got {len(v)}")
    if not np.isfinite(v).all():
        raise UnitError("mesh vertices must be finite numbers")
    f = _faces(faces, len(v))
    hull_volume(Mesh(_tuples(v, float), ()), (1.0, 1.0, 1.0))  # refuses a flat mesh
    return Mesh(_tuples(v, float), _tuples(f, int))


def _faces(faces: Any, n: int) -> np.ndarray:
    if faces is None or len(faces) == 0:
        return np.zeros((0, 3), dtype=int)
    try:
        f = np.asarray(faces)
    except (TypeError, ValueError):
        raise UnitError("mesh faces are a list of [i, j, k] vertex indices") from None
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
        raise UnitError("mesh faces are a list of [i, j, k] vertex indices (whole numbers)")
    if f.min() < 0 or f.max() >= n:
        raise UnitError(f"a mesh face refers to vertex {int(f.max() if f.max() >= n else f.min())}, but the "
                        f"mesh has vertices 0 to {n - 1}")
    return f.astype(int)


def _tuples(a: np.ndarray, kind: type) -> tuple:
    return tuple(tuple(kind(x) for x in row) for row in a.tolist())


# -- files ------------------------------------------------------------------------------------------------
def read_mesh(path: str | os.PathLike[str]) -> Mesh:
    """Read a ``.obj`` or ``.stl`` (ASCII or binary) file; `UnitError` names the file and what is wrong."""
    path = os.fspath(path)
    suffix = os.path.splitext(path)[1].lower()
    if suffix not in MESH_SUFFIXES:
        raise UnitError(f"mesh file {path!r}: a mesh file is {' or '.join(MESH_SUFFIXES)}")
    if not os.path.isfile(path):
        raise UnitError(f"mesh file {path!r} not found")
    if os.path.getsize(path) > MAX_FILE_BYTES:
        raise UnitError(f"mesh file {path!r} is over {MAX_FILE_BYTES // 2**20} MiB")
    with open(path, "rb") as fh:
        data = fh.read()
    try:
        v, f = _read_obj(data) if suffix == ".obj" else _read_stl(data)
        return make_mesh(v, f)
    except (UnitError, ValueError, IndexError, struct.error, UnicodeDecodeError) as exc:
        raise UnitError(f"mesh file {path!r} cannot be read: {exc}") from None


def _read_obj(data: bytes) -> tuple[list, list]:
    vertices: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    for number, line in enumerate(data.decode("utf-8", errors="strict").splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "v":
            if len(parts) < 4:
                raise ValueError(f"line {number}: a vertex is 'v x y z'")
            vertices.append([float(x) for x in parts[1:4]])
        elif parts[0] == "f":
            if len(parts) < 4:
                raise ValueError(f"line {number}: a face has at least 3 vertices")
            idx = []
            for item in parts[1:]:
                i = int(item.split("/", 1)[0])
                idx.append(i - 1 if i > 0 else len(vertices) + i)  # 1-based, or negative: from the end
            faces += [(idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1)]  # polygons as fans
    if not vertices:
        raise ValueError("no vertices ('v x y z' lines)")
    return vertices, faces


def _read_stl(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    if len(data) >= 84 and len(data) == 84 + 50 * struct.unpack_from("<I", data, 80)[0]:  # binary
        n = struct.unpack_from("<I", data, 80)[0]
        rec = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
        corners = np.frombuffer(data, dtype=rec, count=n, offset=84)["v"].reshape(-1, 3).astype(float)
    elif data.lstrip().startswith(b"solid"):
        words = data.decode("ascii").split()
        corners = np.array([[float(x) for x in words[i + 1:i + 4]] for i, w in enumerate(words) if w == "vertex"])
    else:
        raise ValueError("neither a binary STL (80-byte header, count, 50 bytes a triangle) nor an ASCII one")
    if len(corners) == 0 or len(corners) % 3:
        raise ValueError("no triangles")
    unique, index = np.unique(corners, axis=0, return_inverse=True)  # an STL repeats shared corners
    return unique, index.reshape(-1, 3)


# -- convex hull and mass -----------------------------------------------------------------------------------
@functools.lru_cache(maxsize=64)
def convex_hull(mesh: Mesh, scale: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of the convex hull of the mesh's vertices times ``scale``: the hull's own
    vertices and its triangles, counter-clockwise seen from outside (Qhull, through SciPy)."""
    from scipy.spatial import ConvexHull, QhullError

    p = np.asarray(mesh.vertices, dtype=float) * np.asarray(scale, dtype=float)
    try:
        hull = ConvexHull(p)
    except (QhullError, ValueError):
        raise UnitError("a mesh must span a volume (its vertices lie on a plane, a line or a point)") from None
    tri = hull.simplices.copy()
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), hull.equations[:, :3]) < 0  # Qhull: outward normals
    tri[inward] = tri[inward][:, ::-1]
    used = np.unique(tri)
    remap = np.full(len(p), -1)
    remap[used] = np.arange(len(used))
    return p[used], remap[tri]


def hull_volume(mesh: Mesh, scale: tuple[float, float, float]) -> float:
    return mass_properties(*convex_hull(mesh, scale))[0]


def mass_properties(points: np.ndarray, tri: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(volume, centre, inertia about the centre per unit density) of a closed mesh with outward
    triangles (a sum of signed tetrahedra from the points' mean)."""
    o = points.mean(axis=0)
    a, b, c = points[tri[:, 0]] - o, points[tri[:, 1]] - o, points[tri[:, 2]] - o
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    volume = float(vol.sum())
    if not volume > 0 or not math.isfinite(volume):
        raise UnitError("a mesh must span a volume")
    s = a + b + c
    centre = (vol[:, None] * s).sum(axis=0) / (4.0 * volume)
    second = sum(np.einsum("t,ti,tj->ij", vol, x, x) for x in (a, b, c, s)) / 20.0  # the integral of r r^T
    second -= volume * np.outer(centre, centre)
    inertia = np.trace(second) * np.eye(3) - second
    return volume, centre + o, inertia
