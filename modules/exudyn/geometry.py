"""Geometry for the Exudyn core, in plain numpy: poses, mass properties of primitives, and the contact
primitives (spheres and triangles) each shape is made of.

A pose is ``(p, q)``: position (3,) and unit quaternion (4, w-x-y-z); ``compose(a, b)`` is the pose of
frame b's child in a's parent, ``a * b``. Masses default to a density of 1000 kg/m^3, as in MuJoCo, so
a scene without masses weighs the same on both cores.

Contact shapes (Exudyn's general contact knows spheres, and triangles that spheres hit):

- sphere: one sphere;
- box: its 12 face triangles and 8 corner spheres, inset so the faces stay flush (corners rounded by
  ``CORNER_FRACTION`` of the smallest half edge);
- cylinder: a triangle mesh and a ring of ``RIM_SPHERES`` spheres on each rim;
- capsule: a triangle mesh and spheres of its radius along its axis, about ``CAPSULE_SPACING``
  radii apart (spheres of one body must not overlap: that would be a contact with itself; between
  them a thing smaller than the radius could poke into the capsule's side);
- plane: two static triangles;
- mesh: the convex hull of its vertices (as MuJoCo collides it): the hull's triangles, and a sphere in
  each hull corner, tangent to the faces there, of ``CORNER_FRACTION`` of the hull's smallest distance
  from its centre to a face (and less than half its shortest edge: spheres of one body must not overlap);
  ``support`` is the number of corners of its largest flat side (more where its corners are lighter
  to push than a cube's: `_light_corners`).

``support`` is how many of a shape's spheres carry it at rest on a flat floor; the core divides a
body's contact stiffness among them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dynabrain.orchestrator.kernel.meshes import Mesh, convex_hull
from dynabrain.orchestrator.kernel.meshes import mass_properties as mesh_mass

DENSITY = 1000.0
"""kg/m^3 of a body without a mass (MuJoCo's default)."""
CORNER_FRACTION = 0.25
"""Corner-sphere radius of a box, as a fraction of its smallest half edge."""
RIM_SPHERES = 8
"""Spheres on each rim of a cylinder."""
MESH_SEGMENTS = 8
"""Segments around a cylinder or capsule mesh (every triangle and sphere costs each step; on a link of
a kinematic tree more, as each one's place is a forward kinematics)."""
CAPSULE_SPACING = 3.0
"""Distance between the spheres along a capsule, in radii."""
PLANE_HALF = 100.0
"""Half size (m) of the triangles of an infinite plane."""

SHAPES_WITH_CONTACT = ("plane", "box", "sphere", "capsule", "cylinder", "mesh")
Pose = tuple[np.ndarray, np.ndarray]
IDENTITY: Pose = (np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))


# -- quaternions and poses ------------------------------------------------------------------------------------
def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternion product ``a * b`` (w-x-y-z), for single quaternions or stacks (..., 4)."""
    w1, x1, y1, z1 = np.moveaxis(np.asarray(a, dtype=float), -1, 0)
    w2, x2, y2, z2 = np.moveaxis(np.asarray(b, dtype=float), -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def qmul_n(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`qmul` of two stacks (n, 4), faster for the few bodies of a scene."""
    w1, x1, y1, z1 = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    w2, x2, y2, z2 = b[:, 0], b[:, 1], b[:, 2], b[:, 3]
    out = np.empty((len(a), 4))
    out[:, 0] = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    out[:, 1] = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
    out[:, 2] = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
    out[:, 3] = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2
    return out


def cross_n(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products of two stacks (n, 3)."""
    out = np.empty((len(a), 3))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def rotate_n(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors (n, 3) rotated by unit quaternions (n, 4): v + 2w (u x v) + 2 u x (u x v)."""
    u = q[:, 1:]
    uv = cross_n(u, v)
    return v + 2.0 * (q[:, :1] * uv + cross_n(u, uv))


def rotvec_to_quat_n(v: np.ndarray) -> np.ndarray:
    """`rotvec_to_quat` of a stack (n, 3)."""
    angle = np.sqrt(np.einsum("ij,ij->i", v, v))
    half = 0.5 * angle
    small = angle < 1e-8
    scale = np.sin(half) / np.where(small, 1.0, angle)
    scale[small] = 0.5 - angle[small] ** 2 / 48.0
    out = np.empty((len(v), 4))
    out[:, 0] = np.cos(half)
    out[:, 1:] = v * scale[:, None]
    return out


def qconj(q: np.ndarray) -> np.ndarray:
    return np.asarray(q, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (or a stack of them)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def mat_to_quat(m: np.ndarray) -> np.ndarray:
    """Unit quaternion (w >= 0) of a rotation matrix."""
    m = np.asarray(m, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    else:
        i = int(np.argmax([m[0, 0], m[1, 1], m[2, 2]]))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-300))
        q = np.empty(4)
        q[1 + i] = 0.25 * s
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def rotvec_to_quat(v: np.ndarray) -> np.ndarray:
    """Unit quaternions of rotation vectors (..., 3)."""
    v = np.asarray(v, dtype=float)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 0, angle, 1.0), 0.5 - angle * angle / 48.0)
    return np.concatenate([np.cos(half), v * scale], axis=-1)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    q = -q if q[0] < 0 else q
    s = np.linalg.norm(q[1:])
    if s < 1e-12:
        return 2.0 * q[1:]
    return q[1:] * (2.0 * math.atan2(s, q[0]) / s)


def compose(a: Pose, b: Pose) -> Pose:
    """``a * b``: pose b (given in frame a) in a's parent frame."""
    return a[0] + quat_to_mat(a[1]) @ b[0], qmul(a[1], b[1])


def inverse(a: Pose) -> Pose:
    qi = qconj(a[1])
    return -(quat_to_mat(qi) @ a[0]), qi


def pose(p, q=(1.0, 0.0, 0.0, 0.0)) -> Pose:
    q = np.asarray(q, dtype=float)
    return np.asarray(p, dtype=float).copy(), q / np.linalg.norm(q)


def frame_z(axis) -> np.ndarray:
    """A rotation matrix whose third column is the unit ``axis`` (the frame of a joint)."""
    z = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def direction_quat(direction) -> np.ndarray:
    """The quaternion turning the x axis onto ``direction``."""
    d = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    z = frame_z(d)  # its third column is d; make d the first column instead
    return mat_to_quat(np.column_stack([z[:, 2], z[:, 0], z[:, 1]]))


# -- mass properties ------------------------------------------------------------------------------------------
def volume(shape: str, size: tuple[float, ...]) -> float:
    if shape == "box":
        return float(np.prod(size))
    if shape == "sphere":
        return 4.0 / 3.0 * math.pi * size[0] ** 3
    if shape == "cylinder":
        return math.pi * size[0] ** 2 * size[1]
    if shape == "capsule":
        return math.pi * size[0] ** 2 * size[1] + 4.0 / 3.0 * math.pi * size[0] ** 3
    return 0.0


def mass_properties(shape: str, size: tuple[float, ...], mass: float | None) -> tuple[float, np.ndarray]:
    """(mass, inertia about the centre in the body frame) of a primitive; axes of revolution are z."""
    vol = volume(shape, size)
    m = float(mass) if mass is not None else DENSITY * vol
    if shape == "box":
        a, b, c = size
        diag = m / 12.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    elif shape == "sphere":
        diag = np.full(3, 0.4 * m * size[0] ** 2)
    elif shape == "cylinder":
        r, h = size
        diag = np.array([m * (3 * r * r + h * h) / 12.0] * 2 + [0.5 * m * r * r])
    elif shape == "capsule":
        diag = _capsule_inertia(m, *size)
    else:
        return 0.0, np.zeros((3, 3))
    return m, np.diag(diag)


def body_mass(b) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, inertia about the centre of mass, centre of mass) of a body in its frame: a primitive's
    centre is its origin; a mesh's is its convex hull's (uniform density)."""
    if b.shape == "mesh":
        volume, centre, inertia = mesh_mass(*convex_hull(b.mesh, b.scale))
        m = float(b.mass) if b.mass is not None else DENSITY * volume
        return m, inertia * (m / volume), centre
    m, inertia = mass_properties(b.shape, b.size, b.mass)
    return m, inertia, np.zeros(3)


def _capsule_inertia(m: float, r: float, h: float) -> np.ndarray:
    """A cylinder of length h and two hemispheres (their centres of mass 3r/8 from the flat faces)."""
    cyl, sph = math.pi * r * r * h, 4.0 / 3.0 * math.pi * r ** 3
    mc, ms = m * cyl / (cyl + sph), m * sph / (cyl + sph)
    side = mc * (3 * r * r + h * h) / 12.0 + ms * (0.4 * r * r + h * h / 4.0 + 3.0 * h * r / 8.0)
    return np.array([side, side, 0.5 * mc * r * r + 0.4 * ms * r * r])


def combine(parts: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]]) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, centre of mass, inertia about it) of parts (mass, inertia at own centre, centre, rotation),
    all in one frame."""
    total = sum(p[0] for p in parts)
    if total <= 0:
        return 0.0, np.zeros(3), np.zeros((3, 3))
    com = sum(p[0] * p[2] for p in parts) / total
    inertia = np.zeros((3, 3))
    for m, i_own, c, rot in parts:
        d = c - com
        inertia += rot @ i_own @ rot.T + m * (float(d @ d) * np.eye(3) - np.outer(d, d))
    return total, com, inertia


# -- contact shapes -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ContactShape:
    """Spheres (centres (n, 3), one radius each) and a triangle mesh (points, triangles with outward
    normals), in the body frame."""

    centers: np.ndarray
    radii: np.ndarray
    points: np.ndarray
    triangles: np.ndarray
    support: int
    round: bool
    """True when the spheres are the shape's surface (sphere, capsule, cylinder rims), not only corners."""


def contact_shape(shape: str, size: tuple[float, ...]) -> ContactShape:
    if shape == "sphere":
        return ContactShape(np.zeros((1, 3)), np.array([size[0]]), np.zeros((0, 3)), np.zeros((0, 3), int), 1, True)
    if shape == "box":
        return _box(np.asarray(size, dtype=float) / 2)
    if shape == "cylinder":
        return _cylinder(*size)
    if shape == "capsule":
        return _capsule(*size)
    if shape == "plane":
        hx, hy = size if size else (PLANE_HALF, PLANE_HALF)
        pts = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]])
        return ContactShape(np.zeros((0, 3)), np.zeros(0), pts, np.array([[0, 1, 2], [0, 2, 3]]), 0, False)
    raise ValueError(f"no contact shape for {shape!r}")


def body_contact_shape(b) -> ContactShape:
    """The contact shape of a body (a primitive's by its size, a mesh's by its hull)."""
    return mesh_contact_shape(b.mesh, b.scale) if b.shape == "mesh" else contact_shape(b.shape, b.size)


def mesh_contact_shape(mesh: Mesh, scale: tuple[float, float, float]) -> ContactShape:
    points, tris = convex_hull(mesh, scale)
    a, b, c = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
    normal = np.cross(b - a, c - a)
    area = np.linalg.norm(normal, axis=1)
    unit = normal / area[:, None]
    centre = points.mean(axis=0)
    inradius = float(np.min(np.einsum("ij,ij->i", unit, a - centre)))
    edges = np.concatenate([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                            np.linalg.norm(a - c, axis=1)])
    r = min(CORNER_FRACTION * inradius, 0.45 * float(edges.min()))
    centers = np.empty_like(points)
    for i in range(len(points)):  # tangent to the faces at the corner (least squares where more than 3 meet)
        planes = np.unique(np.round(unit[(tris == i).any(axis=1)], 9), axis=0)
        d = np.linalg.lstsq(planes, -np.ones(len(planes)), rcond=None)[0]
        centers[i] = points[i] + r * d
    # the support: the corners of the largest flat side (coplanar triangles summed)
    key = np.round(np.column_stack([unit, np.einsum("ij,ij->i", unit, a)]) / max(r, 1e-12), 3)
    _, which = np.unique(key, axis=0, return_inverse=True)
    largest = int(np.argmax(np.bincount(which.ravel(), weights=area)))
    support = len(np.unique(tris[which.ravel() == largest])) * _light_corners(points, tris, centers)
    return ContactShape(centers, np.full(len(points), r), points, tris, support, False)


BOX_CORNER_SHARE = 1.0 / 5.5
"""The least share of a cube's mass its corner moves (its rotation included: ``m_eff / m``); the
contact damping is stable for it (see `exudyn.contact`)."""


def _light_corners(points: np.ndarray, tris: np.ndarray, centers: np.ndarray) -> float:
    """How much lighter to push than a cube's the lightest corner of a mesh is (at least 1): a mesh
    with long levers about its centre of mass (a tetrahedron's corners) gets its contact stiffness
    and damping shared among as many more spheres, or its damping would make the explicit step
    unstable."""
    volume, com, inertia = mesh_mass(points, tris)
    inv = np.linalg.inv(inertia / volume)
    worst = 0.0
    for arm in centers - com:
        cross = np.array([[0.0, -arm[2], arm[1]], [arm[2], 0.0, -arm[0]], [-arm[1], arm[0], 0.0]])
        worst = max(worst, float(np.linalg.eigvalsh(cross.T @ inv @ cross).max()))
    share = 1.0 / (1.0 + worst)
    return max(1.0, BOX_CORNER_SHARE / share) ** 3  # (measured: a tetrahedron dropped 20 cm settles)


def _box(half: np.ndarray) -> ContactShape:
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    points = signs * half
    r = CORNER_FRACTION * float(half.min())
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))]
    return ContactShape(signs * (half - r), np.full(8, r), points, _outward(points, tris), 4, False)


def _ring(radius: float, z: float, n: int) -> np.ndarray:
    angles = 2 * np.pi * np.arange(n) / n
    return np.column_stack([radius * np.cos(angles), radius * np.sin(angles), np.full(n, z)])


def _cylinder(radius: float, length: float) -> ContactShape:
    r = CORNER_FRACTION * min(radius, length / 2)
    centers = np.vstack([_ring(radius - r, z, RIM_SPHERES) for z in (-length / 2 + r, length / 2 - r)])
    points, tris = _tube([(-length / 2, radius), (length / 2, radius)], caps=True)
    return ContactShape(centers, np.full(len(centers), r), points, tris, RIM_SPHERES, True)


def _capsule(radius: float, length: float) -> ContactShape:
    if length < 2 * radius:  # too short for two spheres that do not overlap: one, around it all
        centers, radii = np.zeros((1, 3)), np.array([radius + length / 2])
    else:
        n = max(2, min(round(length / (CAPSULE_SPACING * radius)) + 1, math.floor(length / (2 * radius)) + 1))
        centers = np.column_stack([np.zeros((n, 2)), np.linspace(-length / 2, length / 2, n)])
        radii = np.full(n, radius)
    profile = [(length / 2 + radius * math.sin(a), radius * math.cos(a)) for a in np.linspace(0, math.pi / 2, 3)]
    profile = [(-z, rr) for z, rr in reversed(profile)] + profile
    points, tris = _tube(profile, caps=False)
    return ContactShape(centers, radii, points, tris, len(centers), True)


def _tube(profile: list[tuple[float, float]], caps: bool) -> tuple[np.ndarray, np.ndarray]:
    """A surface of revolution about z through (z, radius) points, closed at both ends."""
    k = MESH_SEGMENTS
    widen = 1.0 / math.cos(math.pi / k)  # the flat faces, not the corners, lie on the surface
    rings = [_ring(rr * widen, z, k) if rr > 1e-12 else np.array([[0.0, 0.0, z]]) for z, rr in profile]
    points = np.vstack([*rings, [[0.0, 0.0, profile[0][0]]], [[0.0, 0.0, profile[-1][0]]]])
    starts = np.cumsum([0] + [len(r) for r in rings])
    tris: list[tuple[int, int, int]] = []
    for i in range(len(rings) - 1):
        a, b = starts[i], starts[i + 1]
        na, nb = len(rings[i]), len(rings[i + 1])
        for j in range(k):
            if na > 1 and nb > 1:
                tris += [(a + j, a + (j + 1) % k, b + (j + 1) % k), (a + j, b + (j + 1) % k, b + j)]
            elif nb > 1:  # a pole below a ring
                tris.append((a, b + (j + 1) % k, b + j))
            elif na > 1:  # a ring below a pole
                tris.append((a + j, a + (j + 1) % k, b))
    bottom, top = len(points) - 2, len(points) - 1
    if caps or len(rings[0]) > 1:
        tris += [(bottom, starts[0] + (j + 1) % k, starts[0] + j) for j in range(k)]
    if caps or len(rings[-1]) > 1:
        tris += [(top, starts[-2] + j, starts[-2] + (j + 1) % k) for j in range(k)]
    return points, _outward(points, tris)


def _outward(points: np.ndarray, tris) -> np.ndarray:
    """Triangles ordered so that their normals (p1-p0) x (p2-p0) point away from the centre."""
    centre = points.mean(axis=0)
    out = []
    for t in tris:
        a, b, c = (points[i] for i in t)
        normal = np.cross(b - a, c - a)
        out.append(t if normal @ ((a + b + c) / 3 - centre) >= 0 else (t[0], t[2], t[1]))
    return np.array(out, dtype=int)
