"""Animated robots: a robot that a selection (`make`) leaves out follows its motion kinematically.

The paper's d-make freezes what is not selected, but a robot is animated: its joints follow its motion
program, with no dynamics, and the modules that read it (encoders, native sensors, the servo, a ZMP
sensor) keep working. A robot is an object with joints that actuators drive (directly, or through a
fixed tendon: `driven_joints`). How the MuJoCo core does it:

- the robot keeps its joints in the compiled model (a frozen object loses them), so every id, port and
  sensor that reads it stays; its degrees of freedom get a huge armature (`ARMATURE`), so nothing it
  touches moves it within a step (it pushes what it touches as a body of unbounded mass would, at the
  velocity it is animated with), and what would act on it alone is switched off (`make_kinematic`):
  its contacts with the world and the frozen objects, among its own bodies, its limits and its own
  equalities. So it stands where its motion puts it, not on the floor: its force and contact sensors
  read no load, its accelerometer its motion (and gravity);
- after each step (before the kinematics and sensors of the new state are computed) its joints are set
  where the motion puts them: a joint with a motor to its input ``<joint>.target`` (the block
  ``joint_target``, one value per joint with a motor, in actuator order: the order of a servo's
  ``target`` with its default targets, so ``[servo.target, core.joint_target]`` connects them); where the
  input is NaN (its start value) the joint stays where it is; every other joint (the robot's free root,
  joints without a motor) stays where it stood when the robot was left out. Velocities are those of
  the motion over the step (the change of position over the step's time), so contacts see the robot move;
- its free bodies' inputs (``wrench``, ``velocity``) are ignored, as a frozen body's are;
- selecting it again simulates it from where it is, at the velocity it moves with.

Its degrees of freedom are still in MuJoCo's step, so it costs about what simulating the robot costs,
less its contacts and limits (the kid with no servo, a ball beside it: 17 us a tick animated, 31 us
simulated, at a load of 9 on 2 cores); what it saves is the robot's behaviour (it cannot fall, and it
follows its program exactly).
"""

from __future__ import annotations

from typing import NamedTuple

import mujoco
import numpy as np

ARMATURE = 1e6
"""Armature (kg*m^2 for a hinge, kg for a slide or a free joint's translation) of an animated robot's
degrees of freedom: a contact of a 1 kg object at 1 m/s moves it by about a millionth of what it would."""
_HINGE, _SLIDE = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
_TRN_JOINT = (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT))


def make_kinematic(spec: mujoco.MjSpec, entries: list) -> None:
    """Make the robots of ``entries`` (their `FrozenObject` entries) kinematic in a spec: their degrees of
    freedom get `ARMATURE`, and nothing that would act on them alone stays: contacts with the world (and
    the frozen objects fused into it) and among their own bodies are excluded, their joints' and tendons'
    limits switched off, and equalities among their own bodies and joints deleted (a constraint the world
    holds a body to reaches its reference acceleration whatever the body's mass, so these would shake an
    animated robot within a step, and its acceleration and force sensors would read it)."""
    for entry in entries:
        bodies = [b.name for b in entry.bodies]
        joints = {j for j, _values in entry.joints}
        for j in joints:
            joint = spec.joint(j)
            joint.armature, joint.limited = ARMATURE, mujoco.mjtLimited.mjLIMITED_FALSE
        for i, a in enumerate(bodies):
            for b in ("world", *bodies[i + 1:]):
                spec.add_exclude(bodyname1=b, bodyname2=a)
        mine = {*bodies, *joints, "", "world"}
        for eq in list(spec.equalities):
            if {eq.name1, eq.name2} <= mine:
                spec.delete(eq)
        for t in spec.tendons:
            path = t.path
            wraps = [path[i].target for i in range(len(path))]
            if all(w is not None and w.name in joints for w in wraps):
                t.limited = mujoco.mjtLimited.mjLIMITED_FALSE


def motor_joints(model: mujoco.MjModel) -> tuple[str, ...]:
    """Hinge and slide joints an actuator drives directly, in actuator order, each once: the rows of the
    ``joint_target`` input (the servo's default joints, in its order)."""
    out: list[str] = []
    for a in range(model.nu):
        if int(model.actuator_trntype[a]) in _TRN_JOINT:
            j = int(model.actuator_trnid[a, 0])
            if int(model.jnt_type[j]) in (_HINGE, _SLIDE) and model.joint(j).name not in out:
                out.append(model.joint(j).name)
    return tuple(out)


def driven_joints(model: mujoco.MjModel) -> set[str]:
    """Joints an actuator drives: directly, or as a joint of a fixed tendon it pulls."""
    out: set[str] = set()
    joint_wrap = int(mujoco.mjtWrap.mjWRAP_JOINT)
    for a in range(model.nu):
        kind, target = int(model.actuator_trntype[a]), int(model.actuator_trnid[a, 0])
        if kind in _TRN_JOINT:
            out.add(model.joint(target).name)
        elif kind == int(mujoco.mjtTrn.mjTRN_TENDON):
            start, n = int(model.tendon_adr[target]), int(model.tendon_num[target])
            out |= {model.joint(int(model.wrap_objid[w])).name for w in range(start, start + n)
                    if int(model.wrap_type[w]) == joint_wrap}
    return out


class Animation(NamedTuple):
    """Where the animated robots of one compiled structure lie in MuJoCo's arrays (flat indices)."""

    drive_qadr: np.ndarray
    """``qpos`` of the joints with a motor, which follow their ``joint_target`` input ..."""
    drive_dadr: np.ndarray
    """... their ``qvel`` ..."""
    drive_rows: np.ndarray
    """... and their rows in ``joint_target``."""
    hold_qadr: np.ndarray
    """``qpos`` of every other joint of the robots (free roots, joints without a motor) ..."""
    hold_q: np.ndarray
    """... the values they hold (where they stood when the robot was left out) ..."""
    hold_dadr: np.ndarray
    """... and their ``qvel`` (held at 0)."""
    bodies: frozenset[str]
    """The robots' bodies (their free bodies' inputs are ignored)."""


def plan(motors: tuple[str, ...], joint_slices: dict, entries: list) -> Animation | None:
    """The animation of the robots ``entries`` (their `FrozenObject` entries), or None when there are
    none. ``motors`` are the rows of ``joint_target``, ``joint_slices`` the compiled model's joints."""
    if not entries:
        return None
    row = {j: i for i, j in enumerate(motors)}
    drive: list[tuple[int, int, int]] = []
    hold_q: list[float] = []
    hold_qadr: list[int] = []
    hold_dadr: list[int] = []
    for entry in entries:
        for joint, values in entry.joints:
            qa, nq, da, nv = joint_slices[joint]
            if joint in row and nq == 1:
                drive.append((qa, da, row[joint]))
            else:
                hold_qadr += range(qa, qa + nq)
                hold_q += values
                hold_dadr += range(da, da + nv)

    def ints(values) -> np.ndarray:
        return np.array(values, dtype=np.intp)

    return Animation(ints([d[0] for d in drive]), ints([d[1] for d in drive]), ints([d[2] for d in drive]),
                     ints(hold_qadr), np.array(hold_q, dtype=np.float64), ints(hold_dadr),
                     frozenset(b.name for entry in entries for b in entry.bodies))


def animate(a: Animation, qpos: np.ndarray, qvel: np.ndarray, target: np.ndarray, before: np.ndarray,
            dt_s: float) -> None:
    """Put the robots where their motion is after a step of ``dt_s`` that started with their joints with
    a motor at ``before``: those at their targets (where not NaN), the others held still."""
    if len(a.hold_qadr):
        qpos[a.hold_qadr] = a.hold_q
        qvel[a.hold_dadr] = 0.0
    if len(a.drive_qadr):
        want = target[a.drive_rows]
        q = np.where(np.isnan(want), before, want)
        qpos[a.drive_qadr] = q
        qvel[a.drive_dadr] = (q - before) / dt_s
