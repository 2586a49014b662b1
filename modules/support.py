"""Geometry of support: centres of pressure from contact forces, and the support polygon.

Pure functions (no MuJoCo), shared by the ZMP sensor and the benchmark's inline loop. They work on a
handful of feet and contact points per call, every few milliseconds, so they use plain Python floats:
for vectors of two or three numbers that is several times faster than numpy calls.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


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
