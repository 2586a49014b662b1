"""The humanoid's eyes on the table (issue 23): the blocks a stereo camera in a tilted head recognises.

`examples/recognised_blocks.py` recognises blocks from a camera looking straight down: every point of a
top face is at the face's depth. The kid's eye looks down at its table at a slant (its head bowed
45 degrees and the body bent at the hips), so here a top face is a horizontal plane seen obliquely:

1. each colour's top face in both eyes (`recognised_blocks.top_face`, the largest region);
2. its height from the stereo pair: the disparity between the region's outline in the two eyes (the
   middle of its leftmost and rightmost columns; the outline, not the centroid, because a block on top
   hides part of the face below it, and not the same part from each eye);
3. every pixel of the face back-projected onto that horizontal plane (the ray through the pixel from the
   left eye), and the points' smallest enclosing rectangle (OpenCV's ``minAreaRect``) for the block's
   centre, length, width and heading;
4. what each block stands on: the highest face seen below its top whose rectangle holds its centre, or
   the table (the brain's own model knows its table's height); its height is the difference.

A scene that makes no sense is an error naming the blocks (`SceneError`): two blocks in the same place
(their boxes overlap), or a block that floats (nothing seen under it, and taller than `MAX_HEIGHT_M`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from recognised_blocks import HUES, MIN_PIXELS, Block, top_face

from dynabrain.modules.stereo import largest_region, to_world, triangulate
from dynabrain.orchestrator import DynabrainError, World

MAX_HEIGHT_M = 0.08
"""A block taller than this has nothing under it that the eyes saw: it floats."""
OVERLAP_M = 0.003
"""Two blocks' boxes may touch (they rest on each other), not interpenetrate by more than this."""


class SceneError(DynabrainError):
    """Recognised blocks that cannot be: overlapping, floating; the message names them."""


@dataclass(frozen=True)
class Face:
    """A top face seen in both eyes: its colour, height (m), the rectangle on the table plane, pixels."""

    colour: str
    top_m: float
    centre: tuple[float, float]
    size: tuple[float, float]
    yaw: float
    pixels: int
    disparity_px: float


def faces(world: World, eyes: str = "eyes") -> list[Face]:
    """Every block colour whose top face both eyes see (steps 1-3 of the module docstring)."""
    g = world.get
    focal, center, baseline = float(g(f"{eyes}.focal")), g(f"{eyes}.center"), world.modules[eyes].baseline
    pos, rot = g(f"{eyes}.left.pos"), g(f"{eyes}.rot")
    seen = []
    for colour in HUES:
        left, right = (largest_region(top_face(g(f"{eyes}.{eye}.rgb"), colour)) for eye in ("left", "right"))
        if left is None or right is None or min(left.pixels, right.pixels) < MIN_PIXELS:
            continue
        ul, ur = np.nonzero(left.mask)[1], np.nonzero(right.mask)[1]
        disparity = float(ul.min() + ul.max() - ur.min() - ur.max()) / 2
        if disparity <= 0:
            continue
        middle = to_world(triangulate(left.centroid[0], left.centroid[1], disparity, focal, center, baseline),
                          pos, rot)
        top = float(middle[2])
        v, u = np.nonzero(left.mask)
        rays = np.stack([(u + 0.5 - center[0]) / focal, (v + 0.5 - center[1]) / focal, np.ones(len(u))], -1) @ rot.T
        points = pos + ((top - pos[2]) / rays[:, 2])[:, None] * rays
        (cx, cy), (a, b), angle = cv2.minAreaRect(points[:, :2].astype(np.float32))
        pixel = (pos[2] - top) / focal  # about one pixel's footprint on the face
        a, b, yaw = a + 0.5 * pixel, b + 0.5 * pixel, math.radians(angle)
        if a < b:
            a, b, yaw = b, a, yaw + math.pi / 2
        period = math.pi / 2 if a - b < 2 * pixel else math.pi
        yaw = (yaw + period / 2) % period - period / 2
        seen.append(Face(colour, top, (float(cx), float(cy)), (float(a), float(b)), yaw, left.pixels, disparity))
    return seen


def blocks(seen: list[Face], table_top_m: float) -> list[Block]:
    """The blocks the faces are (step 4): each stands on the highest face below it that holds its centre,
    or on the table. Raises `SceneError` for blocks that overlap or float."""
    out: list[Block] = []
    for face in sorted(seen, key=lambda f: f.top_m):
        under = [b for b in out if b.pos[2] + b.size[2] / 2 < face.top_m - 0.005 and _holds(b, face.centre)]
        floor = max((b.pos[2] + b.size[2] / 2 for b in under), default=table_top_m)
        height = face.top_m - floor
        if height > MAX_HEIGHT_M:
            raise SceneError(f"recognised block {face.colour!r} floats: its top is {face.top_m:.3f} m high and "
                             f"nothing seen is under it ({height * 1000:.0f} mm above "
                             f"{'the table' if not under else repr(under[-1].colour)})")
        out.append(Block(face.colour, (face.size[0], face.size[1], height), (face.centre[0], face.centre[1],
                                                                              floor + height / 2), face.yaw))
    check(out)
    return out


def check(found: list[Block]) -> None:
    """`SceneError` naming the first two blocks whose boxes overlap (more than `OVERLAP_M` each way)."""
    for i, a in enumerate(found):
        for b in found[i + 1:]:
            if _overlap(a, b):
                raise SceneError(f"recognised blocks {a.colour!r} and {b.colour!r} overlap: {a.colour} at "
                                 f"{np.round(a.pos, 3).tolist()} size {np.round(a.size, 3).tolist()}, {b.colour} at "
                                 f"{np.round(b.pos, 3).tolist()} size {np.round(b.size, 3).tolist()} (m)")


def _holds(block: Block, xy: tuple[float, float]) -> bool:
    """Whether ``xy`` lies over the block's top face."""
    c, s = math.cos(block.yaw), math.sin(block.yaw)
    dx, dy = xy[0] - block.pos[0], xy[1] - block.pos[1]
    return abs(c * dx + s * dy) <= block.size[0] / 2 and abs(-s * dx + c * dy) <= block.size[1] / 2


def _overlap(a: Block, b: Block) -> bool:
    """Boxes overlap: their heights and their footprints (separating axes of two rectangles) both do."""
    if abs(a.pos[2] - b.pos[2]) >= (a.size[2] + b.size[2]) / 2 - OVERLAP_M:
        return False
    for yaw in (a.yaw, b.yaw):
        axes = (np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)]))
        for axis in axes:
            ra, rb = (_radius(x, axis) for x in (a, b))
            if abs(float(np.dot(np.subtract(a.pos[:2], b.pos[:2]), axis))) >= ra + rb - OVERLAP_M:
                return False
    return True


def _radius(block: Block, axis: np.ndarray) -> float:
    c, s = math.cos(block.yaw), math.sin(block.yaw)
    return (abs(axis @ np.array([c, s])) * block.size[0] + abs(axis @ np.array([-s, c])) * block.size[1]) / 2
