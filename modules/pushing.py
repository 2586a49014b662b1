"""A hand push: a humanoid's hand moves a block through contact, the motion made when the push begins.

The planner's action for the humanoid block task (issue 23, the paper's Fig. 22): "push ``block``
``direction`` ``speed``". Set the run-time parameter ``push`` to such a command (``"blue left fast"``)
and at the next step the module makes the motion from where things are then: the block's pose in the
core, the robot's configuration. Five keyframes, each solved by whole-body inverse kinematics
(`modules.whole_body`: both feet held where they are, the centre of mass over the middle of the
soles, the joint ranges kept), each chained from the last:

1. *above*: the hand's tip over the contact point, clear of the stack;
2. *lower*: the tip beside the block, on the side the push comes from, just above the block's bottom:
   a block taller than the hand is pushed low (`TIP_LOW_M`: the hand's top stays under what stands on
   it), a shorter one a little higher (`TIP_ABOVE_BOTTOM_M`: clear of the block it stands on);
3. *push*: the tip moved ``PUSH_M`` in the direction, through the block (contact physics moves it; the
   block takes no input);
4. *lift*: the tip up again where the push ended;
5. *home*: the program's own pose (no offset).

The motion (minimum-jerk between keyframes, `modules.motion`) is played as offsets from ``home`` on
the ``q_ref`` output, which the servo adds to its program (``servo.q_ref``): the servo's program
holds the standing pose (``home``), the push moves the joints away from it and back. A push is slow
(`DURATIONS`) or fast (the push keyframe in a fraction of the time: the block is hit, and what stands
on it may stay behind).

The servo adds ``q_ref`` to its target but takes no rate with it, where a ``sequence`` of its own
feeds its program's rate forward (``kd * rate``). With ``lead`` set to the servo's ``kd / kp``, the
offsets carry ``lead * rate`` too, and the servo's command, ``kp (target - q) - kd qd``, is the one it
gives playing the push's poses as its own sequence (`program`): what a robot that takes the program
plays (the robot link sends a servo's sequence to the robot).

Which hand: a push to the left (+y) is made by the right hand from the block's right side, a push to
the right by the left hand, a push away (+x) by the hand on the block's side.

A keyframe the inverse kinematics cannot reach (out of reach, a foot that would have to move, the
centre of mass off the support) is not an error: the module plays nothing and says so on
``unreached`` (the keyframe's number, 1..5; 0 when every keyframe was reached). A brain's planner
treats that as a failed action (infinite cost, with the reason).

Outputs: ``q_ref`` (n,) rad, offsets for the servo's joints (n = its joints; targets: joint names or
patterns, default every joint with a motor, in actuator order, as the servo takes them);
``pushing`` () 1 while a motion plays; ``unreached`` () 1 (see above); ``pushes`` () pushes begun.
Parameters: ``home`` (the servo's standing pose: {joint: degrees}), ``push`` (run-time).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.module import Module, Param, Port, SetupContext

from .ik import Target
from .motion import Motion, MotionError, parse_motion, parse_pose
from .mujoco.access import MujocoLink, fail
from .whole_body import WholeBody

DIRECTIONS = {"left": (0.0, 1.0), "right": (0.0, -1.0), "away": (1.0, 0.0)}
"""Push directions in the world frame (x forward from the robot, y to its left)."""
SPEEDS = ("slow", "fast")
PUSH_M = 0.075
"""How far the hand's tip travels in the push keyframe."""
STANDOFF_M = 0.036
"""The tip's distance from the block's face before the push: the hand's half width (2 cm) and 16 mm to spare
(a hand lowered onto the block's edge instead of beside it lands on it, and the robot tips over)."""
HAND_M = 0.05
"""The hand's length from its tip (kid.xml: a 5 cm box above the tip)."""
TIP_LOW_M = 0.005
"""The tip's height over the bottom of a block taller than the hand (by `TIP_LOW_M` and more)."""
TIP_ABOVE_BOTTOM_M = 0.012
"""The tip's height over the bottom of a shorter block: the hand may lean, and its lower corner dips."""
FREE_HAND = {"l_hand_tip": (0.0, 0.13, 0.27), "r_hand_tip": (0.0, -0.13, 0.27)}
"""Where the other hand's tip is held while one pushes (world frame, m): beside the hip, back from the
table (left to the posture alone, it hangs forward and hits the table's edge as the body leans)."""
CLEAR_M = 0.06
"""The *above* keyframe: this much over the pushed block's top (over the stack's top too)."""
DURATIONS = {"slow": (0.4, 0.3, 0.6, 0.25, 0.4), "fast": (0.4, 0.3, 0.12, 0.25, 0.4)}
"""Seconds of each keyframe's move (above, lower, push, lift, home)."""
KEYFRAMES = ("above", "lower", "push", "lift", "home")


@dataclass(frozen=True)
class PushCommand:
    """A parsed ``push`` parameter: ``block`` (a body of the core), ``direction``, ``speed``."""

    block: str
    direction: str
    speed: str

    @classmethod
    def parse(cls, text: Any, where: str) -> PushCommand:
        words = str(text).split() if isinstance(text, str) else []
        if len(words) != 3 or words[1] not in DIRECTIONS or words[2] not in SPEEDS:
            raise ValueError(f"{where}: a push is 'BLOCK DIRECTION SPEED' (directions {', '.join(DIRECTIONS)}; "
                             f"speeds {', '.join(SPEEDS)}), got {text!r}")
        return cls(*words)

    @property
    def seconds(self) -> float:
        """How long the motion plays."""
        return sum(DURATIONS[self.speed])


class HandPush(Module):
    """A block pushed by a hand, the motion solved by whole-body IK when the push begins (see the
    module docstring)."""

    PARAMS = (
        Param("home", None, doc="the servo's standing pose ({joint: degrees}); offsets are from it"),
        Param("push", "", runtime=True, doc="'BLOCK DIRECTION SPEED' (blue left fast): begins at the next step"),
        Param("lead", 0.0, unit="s", dimension="time",
              doc="the servo's kd / kp: the motion's rate times this is added to q_ref (see the module docstring)"),
    )

    def __init__(self, name: str, **kwargs: Any):
        super().__init__(name, **kwargs)
        self._joints: list[str] = []
        self._solver: WholeBody | None = None

    def outputs(self) -> list[Port]:
        n = len(self._joints)
        return [Port("q_ref", (n,), "rad", "joint offsets from home, for the servo's q_ref"),
                Port("pushing", (), "1", "1 while a push plays"),
                Port("unreached", (), "1", "the keyframe (1..5) the IK could not reach; 0: all reached"),
                Port("pushes", (), "1", "pushes begun")]

    def setup(self, ctx: SetupContext) -> None:
        self._link = MujocoLink(self.name, ctx.core)
        self._joints = self._link.expand_joints(self.targets)
        m = self._link.model
        self._slides = [int(m.jnt_type[self._link.lookup("joint", j)]) == int(mujoco.mjtJoint.mjJNT_SLIDE)
                        for j in self._joints]
        try:
            self._home = parse_pose(self.params["home"] or {}, self._joints, self._slides,
                                    np.zeros(len(self._joints)), "home")
        except MotionError as exc:
            raise fail(self.name, f"params.{exc.field}", str(exc)) from None
        self._pending = False
        self._lead = float(self.params["lead"])

    @property
    def program(self) -> list[dict[str, Any]]:
        """The push now playing as a servo ``sequence`` (absolute poses, {joint: degrees}, and durations):
        what a servo without this module plays to make the same motion; empty when none plays."""
        return list(self._steps) if self._motion is not None else []

    def start(self, t_ns: int) -> None:
        self._motion: Motion | None = None
        self._steps: tuple = ()
        self._t0 = t_ns
        for port in ("q_ref", "pushing", "unreached", "pushes"):
            self.out[port][...] = 0.0

    def step(self, t_ns: int, dt_ns: int) -> None:
        if self._pending:
            self._begin(t_ns)
        out = self.out
        if self._motion is None:
            return
        pos, rate = self._motion.at(t_ns - self._t0)
        np.subtract(pos, self._home, out=out["q_ref"])
        if self._lead:
            out["q_ref"] += self._lead * rate
        if t_ns - self._t0 >= self._motion.times[-1]:
            self._motion = None
            out["q_ref"][...] = 0.0
            out["pushing"][...] = 0.0

    def _begin(self, t_ns: int) -> None:
        """Solve the push's keyframes from the state now and start playing them."""
        self._pending = False
        self.out["pushes"][...] += 1
        command = PushCommand.parse(self.params["push"], f"module {self.name!r} [params.push]")
        steps, unreached = self.keyframes(command)
        self.out["unreached"][...] = unreached
        if unreached:
            self._motion = None
            self.out["q_ref"][...] = 0.0
            self.out["pushing"][...] = 0.0
            return
        self._motion = parse_motion(self._home + self.out["q_ref"], steps, self._joints, self._slides)
        self._steps = tuple(steps)
        self._t0 = t_ns
        self.out["pushing"][...] = 1.0

    def keyframes(self, command: PushCommand) -> tuple[list[dict[str, Any]], int]:
        """The servo sequence of a push from the state now, and the first keyframe not reached (0: none)."""
        hand, points = self.tip_path(command)
        free = next(Target(h, pos=p) for h, p in FREE_HAND.items() if h != hand)
        solver = self._whole_body()
        steps, start = [], None
        for i, (point, seconds) in enumerate(zip(points, DURATIONS[command.speed], strict=False)):
            result = solver.solve([Target(hand, pos=point), free], start=start)
            if not result.reached:
                return [], i + 1
            steps.append(result.step(f"{seconds}s"))
            start = result
        home = {j: math.degrees(float(v)) for j, v in zip(self._joints, self._home, strict=True)}
        steps.append({"pose": home, "duration": f"{DURATIONS[command.speed][-1]}s"})
        return steps, 0

    def tip_path(self, command: PushCommand) -> tuple[str, list[np.ndarray]]:
        """The hand and its tip's four targets (above, lower, push, lift) for a push of the block as it is now."""
        m, d = self._link.model, self._link.data
        body = self._link.lookup("body", command.block)
        geom = int(m.body_geomadr[body])
        half = np.array(m.geom_size[geom])
        centre, rot = np.array(d.xpos[body]), np.array(d.xmat[body]).reshape(3, 3)
        direction = np.array([*DIRECTIONS[command.direction], 0.0])
        reach = float(np.sum(np.abs(rot.T @ direction) * half))  # the box's half extent along the push
        bottom = centre[2] - float(np.sum(np.abs(rot[2]) * half))
        top = centre[2] + float(np.sum(np.abs(rot[2]) * half))
        side = centre[1] if command.direction == "away" else -direction[1]
        hand = "l_hand_tip" if side > 0 else "r_hand_tip"
        lower = centre - direction * (reach + STANDOFF_M)
        lower[2] = bottom + (TIP_LOW_M if top - bottom >= HAND_M + 2 * TIP_LOW_M else TIP_ABOVE_BOTTOM_M)
        pushed = lower + direction * PUSH_M
        above, lift = lower.copy(), pushed.copy()
        above[2] = lift[2] = top + CLEAR_M
        return hand, [above, lower, pushed, lift]

    def _whole_body(self) -> WholeBody:
        if self._solver is None:
            self._solver = WholeBody(self._link.core, self._joints)
        return self._solver

    def get_state(self) -> tuple:
        return (self._t0, self._motion, self._pending, self._steps)

    def set_state(self, state: tuple) -> None:
        self._t0, self._motion, self._pending, self._steps = state

    def set_param(self, name: str, value: Any, *, running: bool = True) -> None:
        if name == "push" and value:
            PushCommand.parse(value, f"module {self.name!r} [params.push]")  # a bad command fails here, not later
        super().set_param(name, value, running=running)

    def on_param(self, name: str, value: Any) -> None:
        if name == "push" and value:
            self._pending = True

    def fork(self, memo: dict) -> HandPush:
        """A fork's module: the same configuration on the copied core; its solver is made again when needed."""
        twin = copy.copy(self)
        memo[id(self)] = twin
        twin.bind_ports(None)
        twin._link = copy.deepcopy(self._link, memo)
        twin._solver = None
        return twin

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_solver"] = None
        return state
