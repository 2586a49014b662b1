"""Angle-vector motion programs, as the paper's motion programs send them to the servo.

A *pose* (angle-vector) gives one value per joint of the servo, either

- a list of ``n`` values in the servo's joint order, or
- a mapping ``{joint: value}``; joints it does not name keep their value in the pose before it.

A value is an angle in **degrees** when it is a plain number (as EusLisp angle-vectors and the
scene's hinge ranges are), or a quantity with a unit (``0.5rad``, ``30deg``); for a slide joint a plain
number is metres (``25mm`` works too).

A *sequence* is a list of steps ``{pose: ..., duration: 0.5s}`` (or ``[pose, duration]``): each step
moves from the previous pose to its own in ``duration``, along a minimum-jerk profile (zero velocity
and acceleration at both ends) or linearly; after the last step the last pose is held, or, with
``loop``, the sequence starts again from its first step (moving from the last pose to the first).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dynabrain.orchestrator.kernel.errors import DynabrainError, UnitError
from dynabrain.orchestrator.kernel.suggest import did_you_mean
from dynabrain.orchestrator.kernel.units import parse_duration_ns, parse_quantity

INTERPOLATIONS = ("minjerk", "linear")


class MotionError(DynabrainError):
    """A pose or sequence that does not fit the joints; ``field`` says where (``sequence[2].pose``)."""

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(message)


def parse_value(value: Any, slide: bool, field: str) -> float:
    """One joint value in SI (rad or m)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise MotionError(field, f"expected a number or a quantity like '30deg', got {value!r}")
    if isinstance(value, str):
        try:
            return parse_quantity(value, "length" if slide else "angle")
        except UnitError as exc:
            raise MotionError(field, str(exc)) from None
    return float(value) if slide else math.radians(float(value))


def parse_pose(value: Any, joints: Sequence[str], slides: Sequence[bool], base: np.ndarray, field: str) -> np.ndarray:
    """An angle-vector in SI from a list or a mapping (see the module docstring)."""
    n = len(joints)
    if isinstance(value, Mapping):
        pose = base.copy()
        index = {j: i for i, j in enumerate(joints)}
        for key, v in value.items():
            if key not in index:
                raise MotionError(f"{field}.{key}", f"no joint {key!r} in the servo's joints"
                                  + did_you_mean(str(key), joints) + f" ({n} joints: {', '.join(joints[:8])}"
                                  + (", ...)" if n > 8 else ")"))
            pose[index[key]] = parse_value(v, slides[index[key]], f"{field}.{key}")
        return pose
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise MotionError(field, f"an angle-vector of {len(value)} values for {n} joints "
                              f"({', '.join(joints[:8])}{', ...' if n > 8 else ''})")
        return np.array([parse_value(v, s, f"{field}[{i}]") for i, (v, s) in enumerate(zip(value, slides,
                                                                                            strict=True))])
    raise MotionError(field, f"a pose is a list of {n} values or a mapping joint: value, got {value!r}")


@dataclass(frozen=True)
class Motion:
    """A parsed sequence: ``poses[0]`` is the start pose, step i moves from ``poses[i]`` to
    ``poses[i+1]`` between ``times[i]`` and ``times[i+1]`` (ns from the start)."""

    times: tuple[int, ...]
    poses: np.ndarray
    loop: bool = False
    smooth: bool = True
    still: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    """Zero rates, returned while the last pose is held (read-only)."""

    def __post_init__(self) -> None:
        if self.still is None:
            still = np.zeros(self.poses.shape[1])
            still.setflags(write=False)
            object.__setattr__(self, "still", still)

    @property
    def duration_ns(self) -> int:
        return self.times[-1]


    def at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """(pose in SI, its rate per second) at ``t_ns`` after the start."""
        times, poses = self.times, self.poses
        end = times[-1]
        if t_ns >= end:
            if not self.loop or end == 0:
                return poses[-1], self.still
            t_ns %= end
            if t_ns < times[1]:  # the first step of a repeat starts from the last pose
                return self._blend(poses[-1], poses[1], t_ns, times[1])
        i = bisect.bisect_right(times, t_ns) - 1
        return self._blend(poses[i], poses[i + 1], t_ns - times[i], times[i + 1] - times[i])

    def _blend(self, a: np.ndarray, b: np.ndarray, t_ns: int, span_ns: int) -> tuple[np.ndarray, np.ndarray]:
        s = t_ns / span_ns
        if self.smooth:
            s2 = s * s
            f = s2 * s * (10.0 - 15.0 * s + 6.0 * s2)
            df = 30.0 * s2 * (1.0 - s) * (1.0 - s) / (span_ns * 1e-9)
        else:
            f, df = s, 1.0 / (span_ns * 1e-9)
        delta = b - a
        return a + f * delta, df * delta


def parse_motion(start: np.ndarray, sequence: Any, joints: Sequence[str], slides: Sequence[bool], *,
                 loop: bool = False, interpolation: str = "minjerk", field: str = "sequence") -> Motion:
    """A `Motion` from a scenario's ``sequence`` (a list of ``{pose, duration}`` or ``[pose, duration]``)."""
    if interpolation not in INTERPOLATIONS:
        raise MotionError("interpolation", f"unknown interpolation {interpolation!r}"
                          + did_you_mean(interpolation, INTERPOLATIONS) + f"; one of {', '.join(INTERPOLATIONS)}")
    if sequence is None:
        sequence = []
    if not isinstance(sequence, (list, tuple)):
        raise MotionError(field, f"a sequence is a list of {{pose: ..., duration: ...}} steps, got {sequence!r}")
    poses, times = [np.asarray(start, dtype=np.float64)], [0]
    for i, item in enumerate(sequence):
        where = f"{field}[{i}]"
        if isinstance(item, Mapping):
            unknown = [k for k in item if k not in ("pose", "duration")]
            if unknown or "pose" not in item or "duration" not in item:
                raise MotionError(where, "a step is {pose: ..., duration: ...}"
                                  + (f"; unknown key {unknown[0]!r}" if unknown else ""))
            pose, duration = item["pose"], item["duration"]
        elif isinstance(item, (list, tuple)) and len(item) == 2:
            pose, duration = item
        else:
            raise MotionError(where, f"a step is {{pose: ..., duration: ...}} or [pose, duration], got {item!r}")
        try:
            ns = parse_duration_ns(duration, allow_frequency=False)
        except UnitError as exc:
            raise MotionError(f"{where}.duration", str(exc)) from None
        if ns <= 0:
            raise MotionError(f"{where}.duration", f"a step's duration must be positive, got {duration!r}")
        poses.append(parse_pose(pose, joints, slides, poses[-1], f"{where}.pose"))
        times.append(times[-1] + ns)
    array = np.array(poses)
    array.setflags(write=False)
    return Motion(tuple(times), array, loop=bool(loop) and len(times) > 1, smooth=interpolation == "minjerk")
