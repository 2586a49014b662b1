"""Geometry of support: centres of pressure from contact forces, and the support polygon.

Pure functions (no MuJoCo), shared by the ZMP sensor and the benchmark's inline loop. They work on a
handful of feet and contact points per call, every few milliseconds, so they use plain Python floats:
for vectors of two or three numbers that is several times faster than numpy calls.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


class ContactOverflowError(ValueError):
    """A foot's contact sensor found more contacts than it holds (``foot``: its index)."""

    def __init__(self, foot: int, found: int, num: int):
        super().__init__(f"foot {foot}: {found} contacts found, {num} held")
        self.foot, self.found, self.num = foot, found, num


def feet_support(values: Sequence[float], nums: Sequence[int], min_force: float,
                 min_margin: float) -> list[float]:
    """The ZMP sensor's outputs from the contact sensors of k feet, read in one go: ``values`` holds the
    count of contacts each foot's sensor found, then each foot's normal forces (``nums[i]`` slots of
    foot i, 0 where empty), then each foot's contact points (3 ``nums[i]`` values). A foot is loaded
    when its contacts push with ``min_force`` or more in all. Returns, flat: the ZMP (3; NaN when no
    foot is loaded), each foot's centre of pressure (3 each; NaN when not loaded), each foot's normal
    force (0 when not loaded), inside (1 when the ZMP is ``min_margin`` or more inside the support
    polygon, else 0), margin (m, positive inside; NaN without a polygon), the polygon's centre (3).
    Raises `ContactOverflowError` when a sensor found more contacts than it holds."""
    k = len(nums)
    at_force, at_point = k, k + sum(nums)
    cops: list[float] = []
    forces: list[float] = []
    polygon: list[list[float]] = []
    total = x = y = z = 0.0
    for foot, (num, found) in enumerate(zip(nums, values[:k], strict=True)):
        if found > num:
            raise ContactOverflowError(foot, int(found), num)
        normal, points = values[at_force:at_force + num], values[at_point:at_point + 3 * num]
        at_force, at_point = at_force + num, at_point + 3 * num
        cop, fn = contact_pressure(normal, points)
        if fn >= min_force and fn > 0.0:
            cops += cop
            forces.append(fn)
            total, x, y, z = total + fn, x + cop[0] * fn, y + cop[1] * fn, z + cop[2] * fn
            polygon += [points[3 * j:3 * j + 3] for j in range(num) if normal[j] > 0.0]
        else:
            cops += _NAN3
            forces.append(0.0)
    zmp = (x / total, y / total, z / total) if total > 0.0 else _NAN3
    inside, margin, centre = 0.0, math.nan, _NAN3
    if polygon:
        hull = convex_hull(polygon)
        distance = polygon_margin(zmp, hull)
        if math.isfinite(distance):
            margin = distance
            inside = 1.0 if distance >= min_margin and len(hull) >= 3 else 0.0
        centre = (*polygon_centre(hull), sum(p[2] for p in polygon) / len(polygon))
    return [*zmp, *cops, *forces, inside, margin, *centre]


_NAN3 = (math.nan, math.nan, math.nan)


def contact_pressure(normal: Sequence[float], points: Sequence[float]) -> tuple[list[float], float]:
    """Centre of pressure and normal force of a set of contacts: ``normal`` holds each contact's normal
    force (N; 0 for an empty slot), ``points`` their positions, flat (x0, y0, z0, x1, ...). The centre is
    the mean of the points weighted by the forces, NaN when none pushes."""
    total = x = y = z = 0.0
    for j, f in enumerate(normal):
        if f > 0.0:
            total += f
            x, y, z = x + f * points[3 * j], y + f * points[3 * j + 1], z + f * points[3 * j + 2]
    if total <= 0.0:
        return [math.nan, math.nan, math.nan], 0.0
    return [x / total, y / total, z / total], total


def convex_hull(points: np.ndarray | Sequence[Sequence[float]]) -> list[list[float]]:
    """Vertices [x, y] of the convex hull of points (their x, y), counter-clockwise (Andrew's monotone
    chain; repeated points are dropped). Fewer than three distinct points give those points."""
    if isinstance(points, np.ndarray):
        points = points.tolist()
    pts = sorted(p[:2] for p in points)
    if len(pts) < 3:
        return [p for i, p in enumerate(pts) if i == 0 or p != pts[i - 1]]

    def half(seq: list[list[float]]) -> list[list[float]]:
        out: list[list[float]] = []
        for p in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return lower[:-1] + upper[:-1]


def polygon_margin(point: Sequence[float], hull: Sequence[Sequence[float]]) -> float:
    """Signed distance (m) from a point's (x, y) to the boundary of a convex polygon (counter-clockwise):
    positive inside. For a degenerate polygon (a segment or a point) it is minus the distance to it;
    for no polygon or a NaN point, -inf."""
    px, py = float(point[0]), float(point[1])
    if not hull or not (math.isfinite(px) and math.isfinite(py)):
        return -math.inf
    if len(hull) == 1:
        return -math.hypot(px - hull[0][0], py - hull[0][1])
    if len(hull) == 2:
        (ax, ay), (bx, by) = hull
        ex, ey = bx - ax, by - ay
        s = min(max(((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey), 0.0), 1.0)
        return -math.hypot(px - (ax + s * ex), py - (ay + s * ey))
    margin = math.inf
    for (ax, ay), (bx, by) in zip(hull, hull[1:] + hull[:1], strict=True):
        ex, ey = bx - ax, by - ay
        margin = min(margin, (ex * (py - ay) - ey * (px - ax)) / math.hypot(ex, ey))
    return margin


def polygon_centre(hull: Sequence[Sequence[float]]) -> tuple[float, float]:
    """Mean of a polygon's vertices."""
    n = len(hull)
    return sum(p[0] for p in hull) / n, sum(p[1] for p in hull) / n
