"""Geometry of support: centres of pressure from foot force/torque sensors, and the support polygon.

Pure functions (no MuJoCo), shared by the ZMP sensor and the benchmark's inline loop. They work on a
handful of feet and contact points per call, every few milliseconds, so they use plain Python floats:
for vectors of two or three numbers that is several times faster than numpy calls.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

GRAVITY = (0.0, 0.0, -9.81)


def foot_pressure(site_pos: np.ndarray, site_rot: np.ndarray, force: np.ndarray, torque: np.ndarray,
                  sole_depth: np.ndarray, foot_mass: np.ndarray, foot_com: np.ndarray,
                  gravity: Sequence[float] = GRAVITY) -> tuple[list[list[float]], list[float]]:
    """Centre of pressure and normal ground force of k feet, from 6-axis sensors at their ankles.

    ``site_pos`` (k, 3) and ``site_rot`` (k, 3, 3) or (k, 9) are the sensor sites in the world (rotation
    site -> world); ``force`` and ``torque`` (k, 3) are what the sensors read (MuJoCo's convention: the
    wrench the parent applies to the foot, in the site frame); ``sole_depth`` (k,) is the distance from
    the site down to the sole plane along the site's z axis; the feet's own weights (``foot_mass`` (k,)
    at ``foot_com`` (k, 3)) are added, so that a static stance's centre of pressure is the projection
    of the whole body's centre of mass. The foot is taken as static (its own acceleration is
    neglected). Returns (cop: k points [x, y, z] on each sole plane, in the world; normal force: k
    values in N), as Python lists (a NaN point where the normal force is 0).

    In the site frame (z the sole's normal, the sole plane at z = -d through o = (0, 0, -d)): the
    ground force is ``G = -f - W`` (W the foot's weight), its moment about o is
    ``M = -t - (0, 0, d) x f - (c - o) x W``, and the centre of pressure is ``(-M_y, M_x) / G_z``.
    """
    k = len(site_pos)
    cop: list[list[float]] = []
    fn: list[float] = []
    g0, g1, g2 = map(float, gravity)
    rots, poss, coms = np.asarray(site_rot).reshape(k, 9).tolist(), site_pos.tolist(), foot_com.tolist()
    for r, s, c, f, t, d, m in zip(rots, poss, coms, force.tolist(), torque.tolist(), sole_depth.tolist(),
                                   foot_mass.tolist(), strict=True):
        w0, w1, w2 = m * g0, m * g1, m * g2
        ws0 = r[0] * w0 + r[3] * w1 + r[6] * w2  # the weight in the site frame (R^T w)
        ws1 = r[1] * w0 + r[4] * w1 + r[7] * w2
        ws2 = r[2] * w0 + r[5] * w1 + r[8] * w2
        e0, e1, e2 = c[0] - s[0], c[1] - s[1], c[2] - s[2]
        c0 = r[0] * e0 + r[3] * e1 + r[6] * e2  # the foot's centre of mass relative to o, site frame
        c1 = r[1] * e0 + r[4] * e1 + r[7] * e2
        c2 = r[2] * e0 + r[5] * e1 + r[8] * e2 + d
        mx = -t[0] + d * f[1] - (c1 * ws2 - c2 * ws1)
        my = -t[1] - d * f[0] - (c2 * ws0 - c0 * ws2)
        gz = -f[2] - ws2
        fn.append(gz)
        if gz == 0.0:
            cop.append([math.nan, math.nan, math.nan])
            continue
        p0, p1, p2 = -my / gz, mx / gz, -d
        cop.append([s[0] + r[0] * p0 + r[1] * p1 + r[2] * p2, s[1] + r[3] * p0 + r[4] * p1 + r[5] * p2,
                    s[2] + r[6] * p0 + r[7] * p1 + r[8] * p2])
    return cop, fn


def combined_pressure(cop: Sequence[Sequence[float]], fn: Sequence[float],
                      loaded: Sequence[bool]) -> tuple[float, float, float]:
    """The centre of pressure (x, y, z) of several loaded feet (the ZMP), NaN when none is loaded."""
    total, x, y, z = 0.0, 0.0, 0.0, 0.0
    for (px, py, pz), w, on in zip(cop, fn, loaded, strict=True):
        if on:
            total += w
            x, y, z = x + px * w, y + py * w, z + pz * w
    if total <= 0.0:
        return (math.nan, math.nan, math.nan)
    return (x / total, y / total, z / total)


def convex_hull(points: np.ndarray) -> list[list[float]]:
    """Vertices [x, y] of the convex hull of points (their x, y), counter-clockwise (Andrew's monotone
    chain; repeated points are dropped). Fewer than three distinct points give those points."""
    pts = sorted(np.asarray(points)[:, :2].tolist())
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
