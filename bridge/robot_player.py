"""How the robot emulator plays a motion program (`robot_program`) on its own world, on its own clock.

Two ways, chosen by the emulator's servo:

- a servo that plays programs itself (`dynabrain.modules.servo.Servo`: a run-time ``sequence``) is given
  the program as its ``sequence``, in SI: it begins it at its next step from where its own program
  stands, with the same interpolation and velocity feed-forward as the served world's servo;
- any other servo (the bridge's `PDServo`) has its targets set from the program every control period,
  interpolated here (`modules.motion.Motion`), from the target it holds when the program comes.

The clock is the emulator's world's simulated time, which the emulator keeps with the wall clock.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dynabrain.modules.motion import Motion
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.world import World

from .calls import Rig
from .robot_program import Program


class ProgramPlayer:
    """The program the emulator plays now, and the robot's word on it (`word`, for its ``status``)."""

    def __init__(self, world: World, rig: Rig):
        self._world, self._rig = world, rig
        servo = world.modules[rig.servo]
        spec = servo.param_specs().get("sequence")
        self.by_servo = spec is not None and spec.runtime and hasattr(servo, "slides")
        self._servo = servo
        self._units = ["m" if slide else "rad" for slide in servo.slides] if self.by_servo else []
        self._motion: Motion | None = None  # played here (not by the servo)
        self._t0_ns = 0
        self._end_ns: int | None = None  # world time at which a program that does not loop is done
        self.word: dict[str, Any] | None = None
        """``{seq, state, steps, duration_s, loop, interpolation, reason}``; ``state``: playing, done,
        stopped (a safe stop), replaced (a move, on a servo that does not play programs), ignored (not
        enabled) or refused (stale, or a program its servo cannot play)."""

    @property
    def playing(self) -> bool:
        return self.word is not None and self.word["state"] == "playing"

    def start(self, program: Program, seq: int, target: np.ndarray) -> None:
        """Play ``program`` from now; ``target``: the rig's target now (where a program played here starts)."""
        now = self._world.time_ns
        self.word = {"seq": seq, "state": "playing", **program.describe(), "reason": None}
        if self.by_servo:
            refusal = self._refusal(program)
            if refusal is None:
                try:
                    self._world.set(f"{self._rig.servo}.sequence", self._steps(program))
                except DynabrainError as exc:  # its servo refuses the steps: the robot goes on as it was
                    refusal = f"its servo {self._rig.servo!r} refused the steps: {exc}"
            if refusal is not None:
                self.end("refused", refusal)
                return
        else:
            poses = np.vstack([target, program.poses])
            self._motion = Motion(program.times_ns(), poses, loop=program.loop, smooth=program.smooth)
        self._t0_ns = now
        self._end_ns = None if program.loop else now + program.duration_ns

    def _refusal(self, program: Program) -> str | None:
        """Why the emulator's servo cannot play ``program`` as sent (its interpolation and loop are fixed)."""
        params = self._servo.params
        interpolation = "minjerk" if program.smooth else "linear"
        if params["interpolation"] != interpolation or bool(params["loop"]) != program.loop:
            return (f"its servo {self._rig.servo!r} plays {params['interpolation']} steps with loop "
                    f"{bool(params['loop'])}; the program has {interpolation} steps with loop {program.loop}")
        return None

    def _steps(self, program: Program) -> list[dict[str, Any]]:
        """The servo's ``sequence`` for ``program``: values with their SI unit, so none is read as degrees."""
        return [{"pose": [_quantity(x, unit) for x, unit in zip(pose, self._units, strict=True)],
                 "duration": f"{duration}ns"} for duration, pose in zip(program.durations_ns, program.poses,
                                                                        strict=True)]

    def target(self) -> np.ndarray | None:
        """The rig's target now from a program played here (None when none is, or the servo plays it)."""
        if self._motion is None:
            return None
        return np.array(self._motion.at(self._world.time_ns - self._t0_ns)[0])

    def done(self) -> bool:
        """True once, when a program that does not loop has reached its end (take its last `target` before:
        the robot holds its last pose)."""
        if not self.playing or self._end_ns is None or self._world.time_ns < self._end_ns:
            return False
        self.end("done", None)
        return True

    def end(self, state: str, reason: str | None) -> None:
        """End the program (``state``: done, stopped, replaced); a servo that plays it freezes where its
        program stands when it is stopped."""
        if self.by_servo and self.playing and state == "stopped":
            self._world.set(f"{self._rig.servo}.sequence", [])  # a new, empty program: hold where it is
        self._motion, self._end_ns = None, None
        if self.word is not None:
            self.word = {**self.word, "state": state, "reason": reason}

    def refuse(self, program: Program, seq: int, state: str, reason: str) -> None:
        """A program not played (``ignored``: the robot is not enabled; ``refused``: stale or unplayable)."""
        self.word = {"seq": seq, "state": state, **program.describe(), "reason": reason}


def _quantity(value: float, unit: str) -> str:
    """``value`` as a quantity string the motion parser reads back to the same float."""
    x = float(value)
    return f"{x!r}{unit}" if x == 0.0 or 1e-300 < abs(x) < 1e300 else f"0{unit}"
