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
    Raises `ContactOverflowError` when a sensor found more contacts than it holds.

    Written for its cost on every branch of a batch (one loop over the contacts, the points kept as
    tuples): 7.6 us for two feet of four contacts each, where the first version (a helper call per foot,
    points as lists) took 11.8 on this machine, with the same operations in the same order."""
    k = len(nums)
    at_force, at_point = k, k + sum(nums)
    cops: list[float] = []
    forces: list[float] = []
    points: list[tuple[float, float]] = []  # the support polygon's points (x, y), and the sum of their z
    zsum = 0.0
    total = x = y = z = 0.0
    for foot in range(k):
        num, found = nums[foot], values[foot]
        if found > num:
            raise ContactOverflowError(foot, int(found), num)
        fn = fx = fy = fz = 0.0
        for j in range(num):
            f = values[at_force + j]
            if f > 0.0:
                p = at_point + 3 * j
                fn += f
                fx, fy, fz = fx + f * values[p], fy + f * values[p + 1], fz + f * values[p + 2]
        if fn >= min_force and fn > 0.0:
            cx, cy, cz = fx / fn, fy / fn, fz / fn
            cops += (cx, cy, cz)
            forces.append(fn)
            total, x, y, z = total + fn, x + cx * fn, y + cy * fn, z + cz * fn
            for j in range(num):
                if values[at_force + j] > 0.0:
                    p = at_point + 3 * j
                    points.append((values[p], values[p + 1]))
                    zsum += values[p + 2]
        else:
            cops += _NAN3
            forces.append(0.0)
        at_force, at_point = at_force + num, at_point + 3 * num
    zmp = (x / total, y / total, z / total) if total > 0.0 else _NAN3
    if not points:
        return [*zmp, *cops, *forces, 0.0, math.nan, *_NAN3]
    hull = _hull(points)
    inside, margin = 0.0, math.nan
    distance = polygon_margin(zmp, hull)
    if math.isfinite(distance):
        margin = distance
        inside = 1.0 if distance >= min_margin and len(hull) >= 3 else 0.0
    return [*zmp, *cops, *forces, inside, margin, *polygon_centre(hull), zsum / len(points)]


def _hull(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """`convex_hull` of (x, y) tuples."""
    pts = sorted(points)
    if len(pts) < 3:
        return [p for i, p in enumerate(pts) if i == 0 or p != pts[i - 1]]
    lower, upper = _chain(pts), _chain(pts[::-1])
    return lower[:-1] + upper[:-1]


def _chain(pts: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """One half of Andrew's monotone chain over sorted points: each point that does not turn left from the
    last two (collinear and repeated points too) is dropped."""
    out: list[tuple[float, float]] = []
    for p in pts:
        while len(out) >= 2:
            (ox, oy), (qx, qy) = out[-2], out[-1]
            if not (qx - ox) * (p[1] - oy) - (qy - oy) * (p[0] - ox) <= 0:
                break
            out.pop()
        out.append(p)
    return out


_NAN3 = (math.nan, math.nan, math.nan)


def convex_hull(points: np.ndarray | Sequence[Sequence[float]]) -> list[list[float]]:
    """Vertices [x, y] of the convex hull of points (their x, y), counter-clockwise (Andrew's monotone
    chain; repeated points are dropped). Fewer than three distinct points give those points."""
    if isinstance(points, np.ndarray):
        points = points.tolist()
    return [list(p) for p in _hull([(p[0], p[1]) for p in points])]


def polygon_margin(point: Sequence[float], hull: Sequence[Sequence[float]]) -> float:
    """Signed distance (m) from a point's (x, y) to the boundary of a convex polygon (counter-clockwise):
    positive inside. For a degenerate polygon (a segment or a point) it is minus the distance to it;
    for no polygon or a NaN point, -inf."""
    px, py = float(point[0]), float(point[1])
    if not hull or not (math.isfinite(px) and math.isfinite(py)):
        return -math.inf
    if len(hull) == 1 or (len(hull) == 2 and list(hull[0]) == list(hull[1])):  # (a point, found thrice)
        return -math.hypot(px - hull[0][0], py - hull[0][1])
    if len(hull) == 2:
        (ax, ay), (bx, by) = hull
        ex, ey = bx - ax, by - ay
        s = min(max(((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey), 0.0), 1.0)
        return -math.hypot(px - (ax + s * ex), py - (ay + s * ey))
    margin = math.inf
    ax, ay = hull[0]
    for bx, by in (*hull[1:], hull[0]):  # each edge in turn (a loop, not zip: the ZMP sensor calls this often)
        ex, ey = bx - ax, by - ay
        d = (ex * (py - ay) - ey * (px - ax)) / math.hypot(ex, ey)
        if d < margin:
            margin = d
        ax, ay = bx, by
    return margin


def polygon_centre(hull: Sequence[Sequence[float]]) -> tuple[float, float]:
    """Mean of a polygon's vertices."""
    sx = sy = 0.0
    for x, y, *_ in hull:
        sx += x
        sy += y
    return sx / len(hull), sy / len(hull)
