"""The frames of joints made at run time, and the quaternion arithmetic they need. (Bodies as a brain
writes them, `BodySpec` and its rules, are in `kernel.specs`.)

A joint made at run time (`PhysicsCore.make_joint` with a ``kind`` other than ``weld``) is kept as
`JointFrames`: the joint's frame in each of the two bodies, as they stood when it was made. The
frame's z axis is the joint's axis (a hinge turns about it, a slider slides along it) and its origin
the anchor. Both cores build their joint from these values, so they are engine-neutral.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from .errors import UnitError
from .portable import state_type
from .suggest import did_you_mean

MADE_JOINT_KINDS = ("weld", "hinge", "slider", "ball")
"""Kinds of joint `PhysicsCore.make_joint` makes: weld (rigid), hinge (turns about an axis), slider
(slides along an axis, orientation kept) and ball (turns freely about an anchor)."""
_ALIASES = {"slide": "slider", "fixed": "weld", "revolute": "hinge", "prismatic": "slider", "spherical": "ball"}




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
