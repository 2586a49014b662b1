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

    Written inline (one loop over the contacts, the hull and the margin without helper calls) for its
    cost on every branch of a batch: 6.7 us for two feet of four contacts each where the same
    arithmetic through `contact_pressure`, `convex_hull` and `polygon_margin` took 11.8 (this
    machine); each value is computed by the same operations in the same order as through those."""
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
    count = len(points)
    hull = _hull(points)
    n = len(hull)
    margin, inside = math.nan, 0.0
    px, py = zmp[0], zmp[1]
    if math.isfinite(px) and math.isfinite(py):
        if n == 1 or (n == 2 and hull[0] == hull[1]):  # (three or more points, all the same: a point)
            margin = -math.hypot(px - hull[0][0], py - hull[0][1])
        elif n == 2:
            (ax, ay), (bx, by) = hull
            ex, ey = bx - ax, by - ay
            s = min(max(((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey), 0.0), 1.0)
            margin = -math.hypot(px - (ax + s * ex), py - (ay + s * ey))
        else:
            margin = math.inf
            ax, ay = hull[-1]
            for bx, by in hull:  # (each edge, the closing one first: a minimum is the same in any order)
                ex, ey = bx - ax, by - ay
                d = (ex * (py - ay) - ey * (px - ax)) / math.hypot(ex, ey)
                if d < margin:
                    margin = d
                ax, ay = bx, by
        inside = 1.0 if margin >= min_margin and n >= 3 else 0.0
    sx = sy = 0.0
    for hx, hy in hull:
        sx += hx
        sy += hy
    return [*zmp, *cops, *forces, inside, margin, sx / n, sy / n, zsum / count]


def _hull(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """`convex_hull` of (x, y) tuples (the same vertices in the same order), inline."""
    pts = sorted(points)
    if len(pts) < 3:
        return [p for i, p in enumerate(pts) if i == 0 or p != pts[i - 1]]
    lower: list[tuple[float, float]] = []
    for p in pts:
        while len(lower) >= 2:
            (ox, oy), (qx, qy) = lower[-2], lower[-1]
            if not (qx - ox) * (p[1] - oy) - (qy - oy) * (p[0] - ox) <= 0:
                break
            lower.pop()
        lower.append(p)
    upper: list[tuple[float, float]] = []
    for p in reversed(pts):
        while len(upper) >= 2:
            (ox, oy), (qx, qy) = upper[-2], upper[-1]
            if not (qx - ox) * (p[1] - oy) - (qy - oy) * (p[0] - ox) <= 0:
                break
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


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
    if len(hull) == 1 or (len(hull) == 2 and list(hull[0]) == list(hull[1])):  # (a point, found thrice)
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
