"""What refers to what in a model file's spec, and what goes with an object that is frozen or absent.

A model file's elements refer to its bodies, joints, geoms and sites: actuators and sensors, equalities,
tendons (a fixed tendon's joints; a spatial tendon's sites, wrapping geoms and their side sites), contact
pairs and exclusions, cameras and lights that track a body. When a selection (`make`) changes the model,
what refers to a changed element changes with it, or is refused by name; MuJoCo itself would either
delete it silently or fail to compile ("joint ... not found in tendon 0"):

- a frozen object loses its joints (`prune`): the actuators, sensors and joint equalities on them go,
  and so does a fixed tendon whose joints all froze, with its actuators, sensors and tendon equalities
  (a spatial tendon stays: its sites and geoms are still there, fused into the world); a fixed tendon
  that couples a frozen object's joints with a simulated one's is refused, naming it;
- an absent object is deleted (`leave_out`) with every element that acts only within it (its actuators,
  tendons, equalities, contact pairs and exclusions: a robot taken out with its motors and tendons); an
  element that ties it to what stays (a weld to another object, a tendon or contact pair that spans
  both, a camera elsewhere that tracks it) or reads it (a sensor: a module may read its port) is
  refused, naming it: deleting the object would break that, and freezing it (``others="frozen"``)
  keeps it whole.
"""

from __future__ import annotations

from collections.abc import Iterator

import mujoco

from dynabrain.orchestrator.kernel.errors import DynabrainError

_TRN_JOINT = (mujoco.mjtTrn.mjTRN_JOINT, mujoco.mjtTrn.mjTRN_JOINTINPARENT)
_WORLD = {"", "world"}
"""Names that refer to no object (an element's unused reference, or the world body)."""


def _fail(core: str, message: str) -> DynabrainError:
    return DynabrainError(f"mujoco core {core!r}: {message}")


def tendon_targets(tendon: mujoco.MjsTendon) -> set[str]:
    """The names of the joints, sites and geoms (with their side sites) a tendon runs over."""
    path = tendon.path
    out: set[str] = set()
    for i in range(len(path)):
        wrap = path[i]
        if wrap.target is not None:
            out.add(wrap.target.name)
        side = getattr(wrap, "sidesite", None)  # a wrapping geom's side site (an element, or its name)
        if side:
            out.add(side if isinstance(side, str) else side.name)
    return out - _WORLD


def references(spec: mujoco.MjSpec) -> Iterator[tuple[str, object, set[str]]]:
    """(kind, element, names it refers to) for every element that can refer to bodies, joints, geoms,
    sites, tendons or actuators, in the order in which what they refer to goes: tendons before the
    actuators on them, actuators before the sensors that read them."""
    for t in spec.tendons:
        yield "tendon", t, tendon_targets(t)
    for a in spec.actuators:
        yield "actuator", a, {a.target, getattr(a, "refsite", "") or ""} - _WORLD
    for x in spec.sensors:
        yield "sensor", x, {x.objname, getattr(x, "refname", "") or ""} - _WORLD
    for e in spec.equalities:
        yield "equality", e, {e.name1, e.name2} - _WORLD
    for p in spec.pairs:
        yield "contact pair", p, {p.geomname1, p.geomname2} - _WORLD
    for x in spec.excludes:
        yield "contact exclusion", x, {x.bodyname1, x.bodyname2} - _WORLD
    for kind, items in (("camera", spec.cameras), ("light", spec.lights)):
        for c in items:
            if c.targetbody:
                yield kind, c, {c.targetbody}


def _label(kind: str, element: object) -> str:
    name = getattr(element, "name", "")
    return f"{kind} {name!r}" if name else f"an unnamed {kind}"


def leave_out(core: str, spec: mujoco.MjSpec, absent: dict[str, tuple[str, ...]]) -> set[str]:
    """Delete the absent objects (object -> its bodies) from a model file's spec, with every element
    that acts only within them; the names of the joints that went. Refused (nothing deleted yet for that
    object) when an element ties one to what stays or reads it: see the module docstring."""
    joints: set[str] = set()
    for obj, names in absent.items():
        bodies = [spec.body(n) for n in names]
        mine = set(names)  # the names of the object's bodies, joints, geoms and sites, then what goes with it
        for b in bodies:
            mine |= {x.name for kind in (b.joints, b.geoms, b.sites, b.cameras, b.lights) for x in kind} - _WORLD
        inside = {x.name for b in bodies for x in (*b.cameras, *b.lights)}  # deleted with their body
        going, ties = [], []
        for kind, element, targets in references(spec):
            if kind in ("camera", "light") and element.name in inside:
                continue
            if targets and targets <= mine and kind not in ("sensor", "camera", "light"):
                going.append(element)
                if element.name:
                    mine.add(element.name)  # (an actuator on this tendon, a sensor on this actuator)
            elif mine & targets:
                ties.append(_label(kind, element))
        if ties:
            raise _fail(core, f"make(), field others: 'absent' cannot take object {obj!r} out of the model file: "
                        f"{', '.join(ties[:6])}{', ...' if len(ties) > 6 else ''} "
                        f"refer{'s' if len(ties) == 1 else ''} to it; select it, or make with "
                        "others='frozen' (it stays as a static obstacle)")
        for element in reversed(going):  # sensors before the actuators they read, before their tendons
            spec.delete(element)
        for b in bodies:
            joints |= {j.name for j in b.joints}
        spec.delete(bodies[0])  # the object's top body, with its subtree
    for key in list(spec.keys):  # a keyframe's qpos has the deleted joints' values
        spec.delete(key)
    return joints


def prune(core: str, spec: mujoco.MjSpec, joints: set[str]) -> None:
    """Remove what refers to the joints of frozen objects (``joints``, already deleted from the spec):
    fixed tendons over them, and the actuators, sensors, equalities and keyframes on those joints and
    tendons. A fixed tendon over frozen and simulated joints both is refused, naming it."""
    tendons: set[str] = set()
    for t in list(spec.tendons):
        path = t.path
        wraps = [path[i] for i in range(len(path)) if path[i].type == mujoco.mjtWrap.mjWRAP_JOINT]
        lost = [w for w in wraps if w.target is None or w.target.name in joints]
        if not lost:
            continue
        if len(lost) < len(wraps):
            kept = ", ".join(repr(w.target.name) for w in wraps if w not in lost)
            raise _fail(core, f"make(): tendon {t.name!r} couples joints of an object that freezes with joints "
                        f"{kept} of one that stays simulated; select both objects, or neither")
        tendons.add(t.name)
        spec.delete(t)
    gone = set(joints)  # joints, then the actuators on them or on the tendons that went
    for act in list(spec.actuators):
        if ((act.trntype in _TRN_JOINT and act.target in joints)
                or (act.trntype == mujoco.mjtTrn.mjTRN_TENDON and act.target in tendons)):
            gone.add(act.name)
            spec.delete(act)
    refers = {mujoco.mjtObj.mjOBJ_JOINT: gone, mujoco.mjtObj.mjOBJ_ACTUATOR: gone, mujoco.mjtObj.mjOBJ_TENDON: tendons}
    for sensor in list(spec.sensors):
        if sensor.objname in refers.get(sensor.objtype, ()):
            spec.delete(sensor)
    for eq in list(spec.equalities):
        names = {eq.name1, eq.name2}
        if ((eq.type == mujoco.mjtEq.mjEQ_JOINT and names & joints)
                or (eq.type == mujoco.mjtEq.mjEQ_TENDON and names & tendons)):
            spec.delete(eq)
    for key in list(spec.keys):
        spec.delete(key)
