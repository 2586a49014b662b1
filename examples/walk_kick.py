"""Walking to a ball and kicking it (the paper's Fig. 11): the kid's gait, written as one angle-vector program.

The gait is quasi-static: before a foot leaves the ground the pelvis has moved over the other foot,
slowly (1 s), so that the centre of mass, and with it the ZMP, is over the sole that will carry the
robot alone; the free foot is unloaded (lifted 2 mm in 0.6 s), lifted 2 cm, moved 5 cm past the
standing foot, and lowered to 2 mm above the floor; the next shift of the pelvis sets it down. One step
takes 3.1 s; nothing in it relies on momentum, so the ZMP stays over a sole at every instant. The
kick is the same idea on one foot: the pelvis over the left foot, the right foot drawn back 6 cm and
lifted 3 cm, swung forward 14 cm in 0.25 s (the foot's toe meets the ball on the way), brought back and
set down.

The poses come from the legs' inverse kinematics, solved in closed form for the kid's legs (each a hip
with roll and pitch at one point, a thigh and a shin of 0.11 m, an ankle with pitch and roll at one
point; `leg`): given where each ankle is relative to its hip (the pelvis upright, at a fixed height
over the ankles), the hip roll puts the leg's plane through the ankle, the knee sets the hip-ankle
distance, the hip pitch its direction, and the ankle keeps the sole flat. The pelvis and the feet are
placed in the world (`gait`), the angle-vectors follow.

    .venv/bin/python examples/walk_kick.py            # run scenarios/walk_kick.yaml, print the ZMP margin per phase
    .venv/bin/python examples/walk_kick.py --yaml     # print the servo program that scenarios/walk_kick.yaml holds

`scenarios/walk_kick.yaml` holds the program this prints (tests/test_paper_scenes.py checks they agree).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dynabrain.orchestrator import World, load_world

SCENARIO = Path(__file__).resolve().parents[1] / "scenarios" / "walk_kick.yaml"
THIGH_M = SHIN_M = 0.11
"""The kid's leg (scenarios/models/kid.xml): hip pitch to knee, knee to ankle."""
HIP_Y_M = 0.04
"""The hips' distance from the pelvis's centre line (left +, right -): where the feet stand."""
ARMS = {"l_shoulder_roll": 10, "r_shoulder_roll": -10, "l_elbow": -30, "r_elbow": -30}
"""The arms, as humanoid_stand holds them (degrees)."""


@dataclass(frozen=True)
class Gait:
    """The walk: ``steps`` steps of ``step_m`` past the standing foot (the first from feet side by
    side), the right foot first. Lengths in m, times in s."""

    steps: int = 4
    step_m: float = 0.05
    shift_m: float = 0.045
    """How far the pelvis moves sideways from the centre line, over the standing foot."""
    lift_m: float = 0.02
    unload_m: float = 0.002
    """The free foot first rises this much, slowly, so that its load passes to the other foot gently."""
    hover_m: float = 0.002
    """It is lowered to this height over the floor; the next shift of the pelvis sets it down."""
    leg_height_m: float = 0.20
    """Hip to ankle, vertically (0.22 m with straight legs): the crouch the robot walks in."""
    durations_s: dict[str, float] = field(default_factory=lambda: {
        "crouch": 0.5, "shift": 1.0, "unload": 0.6, "lift": 0.5, "swing": 0.5, "place": 0.5, "stand": 1.0})


@dataclass(frozen=True)
class Kick:
    """The kick with the right foot, standing on the left: drawn back ``back_m`` behind the left ankle
    and lifted ``height_m``, swung to ``forward_m`` in front of it in ``duration_s``."""

    back_m: float = 0.06
    forward_m: float = 0.08
    height_m: float = 0.03
    duration_s: float = 0.25
    windup_s: float = 0.6
    recover_s: float = 0.6


@dataclass(frozen=True)
class Phase:
    """One step of the motion program: a name, the pose reached at its end (degrees, the joints the
    gait moves) and how long it takes."""

    name: str
    pose: dict[str, float]
    duration_s: float


def leg(side: str, ankle: tuple[float, float, float]) -> dict[str, float]:
    """The angles (degrees) of one leg that put its ankle at ``ankle`` (m, from the hip, pelvis frame:
    x forward, y left, z up) with the sole flat (see the module docstring)."""
    ax, ay, az = ankle
    roll = math.atan2(ay, -az)
    h = math.hypot(ay, az)
    reach = math.hypot(ax, h)
    cos_knee = (reach**2 - THIGH_M**2 - SHIN_M**2) / (2 * THIGH_M * SHIN_M)
    knee = math.acos(max(-1.0, min(1.0, cos_knee)))
    pitch = math.atan2(-ax, h) - math.atan2(SHIN_M * math.sin(knee), THIGH_M + SHIN_M * math.cos(knee))
    angles = {"hip_roll": roll, "hip_pitch": pitch, "knee": knee, "ankle_pitch": -(pitch + knee), "ankle_roll": -roll}
    return {f"{side}_{joint}": round(math.degrees(a), 2) for joint, a in angles.items()}


def pose(gait: Gait, pelvis: tuple[float, float], left: list[float], right: list[float]) -> dict[str, float]:
    """The angle-vector for the pelvis at ``pelvis`` (x, y) and the ankles at ``left`` and ``right``
    (x, y, height above standing; world frame, m)."""
    px, py = pelvis
    out = dict(ARMS)
    for side, foot, hip_y in (("l", left, HIP_Y_M), ("r", right, -HIP_Y_M)):
        out.update(leg(side, (foot[0] - px, foot[1] - py - hip_y, foot[2] - gait.leg_height_m)))
    return out


def program(gait: Gait = Gait(), kick: Kick | None = Kick()) -> list[Phase]:
    """The whole motion program: crouch, the walk, the kick (``None``: no kick), stand."""
    d = gait.durations_s
    left, right = [0.0, HIP_Y_M, 0.0], [0.0, -HIP_Y_M, 0.0]
    phases = [Phase("crouch", pose(gait, (0.0, 0.0), left, right), d["crouch"])]

    def add(name: str, pelvis: tuple[float, float], duration: float) -> None:
        phases.append(Phase(name, pose(gait, pelvis, left, right), duration))

    for k in range(gait.steps):
        stand, free, side = (left, right, 1.0) if k % 2 == 0 else (right, left, -1.0)
        pelvis = (stand[0], side * gait.shift_m)
        stand[2] = 0.0  # the foot placed last is set down as the pelvis moves over it
        add(f"step {k + 1}: shift", pelvis, d["shift"])
        free[2] = gait.unload_m
        add(f"step {k + 1}: unload", pelvis, d["unload"])
        free[2] = gait.lift_m
        add(f"step {k + 1}: lift", pelvis, d["lift"])
        free[0] = stand[0] + gait.step_m
        add(f"step {k + 1}: swing", pelvis, d["swing"])
        free[2] = gait.hover_m
        add(f"step {k + 1}: place", pelvis, d["place"])
    if kick is not None:
        left[2] = right[2] = 0.0
        pelvis = (left[0], gait.shift_m)
        add("kick: shift", pelvis, d["shift"])
        right[2] = gait.unload_m
        add("kick: unload", pelvis, d["unload"])
        right[0], right[2] = left[0] - kick.back_m, kick.height_m
        add("kick: wind up", pelvis, kick.windup_s)
        right[0] = left[0] + kick.forward_m
        add("kick: kick", pelvis, kick.duration_s)
        right[0], right[2] = left[0], gait.lift_m
        add("kick: recover", pelvis, kick.recover_s)
        right[2] = gait.hover_m
        add("kick: place", pelvis, d["place"])
    left[2] = right[2] = 0.0
    add("stand", ((left[0] + right[0]) / 2, 0.0), d["stand"])
    return phases


def sequence(phases: list[Phase]) -> list[dict]:
    """The servo's ``sequence`` parameter."""
    return [{"pose": p.pose, "duration": f"{p.duration_s:g}s"} for p in phases]


def to_yaml(phases: list[Phase]) -> str:
    """The program as scenarios/walk_kick.yaml writes it: each pose names only the joints that change
    (the servo keeps the others from the pose before), the left leg's on one line and the right's on
    the next, the phase as a comment."""
    lines, before = [], {}
    for p in phases:
        changed = {j: v for j, v in p.pose.items() if before.get(j) != v}
        before = p.pose
        rows = [[f"{j}: {v + 0.0:g}" for j, v in changed.items() if not j.startswith(side)] for side in ("r_", "l_")]
        rows = [", ".join(r) for r in rows if r]
        lines.append("        - pose: {" + (",\n                 ".join(rows)) + "}")
        lines.append(f"          duration: {p.duration_s:g}s   # {p.name}")
    return "\n".join(lines)


@dataclass(frozen=True)
class Outcome:
    """The run: the least ZMP margin in each phase (m; -1 where the ZMP left the support polygon), where
    the feet and the ball ended, and the ball's speed."""

    margins: list[tuple[str, float]]
    left_foot: np.ndarray
    right_foot: np.ndarray
    ball: np.ndarray
    ball_speed: float


def run(world: World, phases: list[Phase], settle_s: float = 1.0) -> Outcome:
    """Play the program on a world built from scenarios/walk_kick.yaml (which already holds it) and
    measure the ZMP margin phase by phase, from 0.1 s after the crouch."""
    dt = world.dt_ns * 1e-9
    ends = np.cumsum([p.duration_s for p in phases])
    margins = {p.name: math.inf for p in phases}
    every = max(1, round(0.01 / dt))  # the ZMP sensor's period
    total = round((ends[-1] + settle_s) / dt)
    while world.tick_count < total:
        world.tick(every)
        t = world.time
        k = int(np.searchsorted(ends, t))
        if t < phases[0].duration_s + 0.1 or k >= len(phases):
            continue
        margin = float(world.get("zmp.margin")) if world.get("zmp.inside") == 1 else -1.0
        name = phases[k].name
        margins[name] = min(margins[name], margin)
    ball_speed = float(np.linalg.norm(world.get("core.ball.linvel")))
    return Outcome([(p.name, margins[p.name]) for p in phases[1:]], world.get("core.l_foot.pos"),
                   world.get("core.r_foot.pos"), world.get("core.ball.pos"), ball_speed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--yaml", action="store_true", help="print the servo program (scenarios/walk_kick.yaml's)")
    args = parser.parse_args()
    phases = program()
    if args.yaml:
        print(to_yaml(phases))
        return
    world = load_world(SCENARIO)
    try:
        world.set("servo.sequence", sequence(phases))  # the same program as the scenario's, from here
        out = run(world, phases)
    finally:
        world.close()
    print(f"{len(phases)} phases, {sum(p.duration_s for p in phases):g} s; least ZMP margin in each (mm):")
    for name, margin in out.margins:
        print(f"  {name:<18} {'outside' if margin < 0 else f'{margin * 1000:5.1f}'}")
    walk = [m for name, m in out.margins if name.startswith("step")]
    print(f"walking: the ZMP stayed inside the support polygon, at least {min(walk) * 1000:.1f} mm from its edge"
          if min(walk) >= 0 else "walking: the ZMP left the support polygon")
    print(f"feet at x = {out.left_foot[0]:.3f} (left), {out.right_foot[0]:.3f} (right) m; the ball at "
          f"{np.round(out.ball, 3)} m, rolling at {out.ball_speed:.2f} m/s")


if __name__ == "__main__":
    main()
