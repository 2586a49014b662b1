"""A servo's motion program on the robot link: the timed steps the robot plays on its own clock.

When the rig's servo in the served world starts a new program (``world.set("servo.sequence", [...])``:
the servo begins it at its next step, see `dynabrain.modules.servo`), the link sends the robot one
ROBOT_CMD frame with operation ``OP_PROGRAM``: the same steps, resolved to absolute joint values in SI,
so that the robot interpolates them itself instead of following targets streamed by the brain.

Values of the frame (``count = 2 + steps * (1 + n)``, all finite)::

    loop            0 or 1: after its last step the program starts again, moving from its last pose
                    to its first
    interpolation   0 minimum jerk (zero velocity and acceleration at both ends of a step), 1 linear
    then per step:  its duration in ns (a whole number > 0), then the joints' program targets at the
                    step's end (rad or m), in the rig's joint order

The program starts from the robot's own program target when the robot takes it (on the emulator,
where its servo's program stands). ``seq`` and ``stamp`` are those of any command; ``aux`` the deadline
in us: a program older than its deadline is refused, like a move.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import frames
from .protocol import ProtocolError

OP_PROGRAM = 3
"""ROBOT_CMD operation: a motion program (after move 0, stop 1, enable 2)."""
MAX_STEPS = 4096
"""At most this many steps in one program."""
_MINJERK, _LINEAR = 0, 1


@dataclass(frozen=True)
class Program:
    """A motion program as it crosses the link: step k ends at ``poses[k]`` after ``durations_ns[k]``."""

    durations_ns: tuple[int, ...]
    poses: np.ndarray
    """(steps, n) absolute program targets, rad or m."""
    loop: bool = False
    smooth: bool = True
    """Minimum-jerk steps (False: linear)."""

    @property
    def duration_ns(self) -> int:
        """The length of one pass of the program."""
        return sum(self.durations_ns)

    @classmethod
    def of_motion(cls, motion: Any) -> Program:
        """The program of a servo's `Motion` (``times`` from 0, ``poses[0]`` its start pose, not sent)."""
        times = motion.times
        durations = tuple(int(b - a) for a, b in itertools.pairwise(times))
        return cls(durations, np.array(motion.poses[1:], dtype=np.float64), bool(motion.loop), bool(motion.smooth))

    def times_ns(self) -> tuple[int, ...]:
        """Step end times from the program's start, with 0 first (`Motion.times`)."""
        out = [0]
        for d in self.durations_ns:
            out.append(out[-1] + d)
        return tuple(out)

    def describe(self) -> dict[str, Any]:
        return {"steps": len(self.durations_ns), "duration_s": self.duration_ns * 1e-9, "loop": self.loop,
                "interpolation": "minjerk" if self.smooth else "linear"}


def program_cmd(program: Program, *, seq: int, stamp_ns: int, deadline_ns: int) -> bytes:
    """The ROBOT_CMD frame that carries ``program``."""
    steps, n = program.poses.shape
    values = np.empty(2 + steps * (1 + n))
    values[0] = 1.0 if program.loop else 0.0
    values[1] = _MINJERK if program.smooth else _LINEAR
    body = values[2:].reshape(steps, 1 + n)
    body[:, 0] = program.durations_ns
    body[:, 1:] = program.poses
    return frames.robot_cmd(OP_PROGRAM, values, seq=seq, stamp_ns=stamp_ns, deadline_ns=deadline_ns)


def read_program(frame: frames.Frame, joints: int) -> Program:
    """The program of a ROBOT_CMD frame with op ``OP_PROGRAM`` (finite values, checked by `frames.unpack`);
    `ProtocolError` naming what is wrong."""
    values = frame.values
    if frame.aux == 0:
        raise ProtocolError("robot program has no deadline")
    size = values.size - 2
    if size <= 0 or size % (1 + joints):
        raise ProtocolError(f"robot program of {values.size} values is not 2 + steps * (1 + {joints} joints)")
    steps = size // (1 + joints)
    if steps > MAX_STEPS:
        raise ProtocolError(f"robot program of {steps} steps, over the limit of {MAX_STEPS}")
    if values[0] not in (0.0, 1.0) or values[1] not in (_MINJERK, _LINEAR):
        raise ProtocolError(f"robot program: loop {values[0]:g} and interpolation {values[1]:g} must each be 0 or 1")
    body = values[2:].reshape(steps, 1 + joints)
    durations = body[:, 0]
    bad = np.flatnonzero((durations <= 0) | (durations != np.round(durations)) | (durations > 2.0 ** 53))
    if bad.size:
        step = int(bad[0])
        raise ProtocolError(f"robot program step {step}: duration {float(durations[step]):g} ns is not a whole "
                            "number of ns > 0")
    poses = body[:, 1:].copy()
    poses.setflags(write=False)
    return Program(tuple(int(d) for d in durations), poses, bool(values[0] == 1.0), bool(values[1] == _MINJERK))
