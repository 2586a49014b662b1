"""The physics-core interface, engine-neutral, and the scene of primitives both cores build.

A physics core is a Module with a scene. The kernel speaks only these words; the MuJoCo and Exudyn
cores translate them to their engines. Structural edits (`make`, `make_joint`, `no_collision`,
`add_body`, `remove_body`, `set_material`) and run-time parameter changes are part of the core's
state, so history and rollback restore them.

The ports follow the bodies: every body present has its ports, so `add_body` and `remove_body` change
the core's `inputs` and `outputs`. The world then installs a structure with the new ports (values
carried by name, connections to ports that are gone dropped); history keeps the old structure, and
when a rollback installs it the core is bound to the old ports, which it takes back by their names
(`EditedCore`). `ports_for_state` tells an importing world the ports of an exported state.

Ports every core exposes (names are ``<object>.<quantity>``):

- per body ``B``: outputs ``B.pos`` (3, m), ``B.quat`` (4, w-x-y-z), ``B.linvel`` (3, m/s),
  ``B.angvel`` (3, rad/s, world frame); positions and velocities are those of the body's frame origin
  (the centre of mass of a primitive);
- per free body ``B`` (a top-level body with a free joint), inputs a brain acts on it with
  (`body_inputs`; views into the blocks ``body_wrench`` and ``body_velocity``, (n, 6), one row per
  free body in body order):

  - ``B.wrench`` (6: force in N, then torque in N*m; world frame, at the body's centre of mass):
    applied for the whole tick, every engine substep, as long as it holds the value; starts at 0;
  - ``B.velocity`` (6: linear velocity of the body's origin in m/s, then angular velocity in rad/s;
    world frame): at the start of every tick, before the engine steps, each component that is not NaN
    becomes the body's velocity; NaN components are left as the motion has them. It starts all NaN
    (nothing is set), and a value stays set, applied again at the start of each tick, until NaN is
    written back: a pusher that moves a block at a speed writes the speed once. Forces act during the
    tick as usual (a body held at a speed is still slowed by what it hits within the tick).

  Both are inputs like any other: connected from a module, set by `World.set` or a scenario's ``set``
  event, saved with the bus (history, rollback, fork, logs). A body frozen by `make` ignores them. A
  body welded to other free bodies (`make_joint`) moves them with it: a velocity set moves them all
  as one rigid body, a wrench pushes the whole (Exudyn: the merged rigid body; MuJoCo: through the
  weld's constraint). Welded to something static or to a jointed link, it is held there (Exudyn
  ignores its inputs; in MuJoCo the weld's constraint fights them);
- per hinge / slide joint ``J``: outputs ``J.q`` (rad or m), ``J.qd``; input ``J.force``
  (N*m or N, a generalised force added at the joint);
- engine-specific extras (MuJoCo actuators ``A.ctrl``, sensors ``sensor.S``) where the engine has them.

Run-time parameters every core has: ``friction`` (sliding coefficient, all contacts),
``restitution`` (coefficient of restitution of contacts, 0..1, mapped so a measured bounce follows
it), ``gravity`` (3-vector, m/s^2), ``substeps`` (engine steps per module step). A body may have its
own ``friction`` and ``restitution`` (`BodySpec`, `set_material`; ``World.set("core.<body>.friction",
...)``): they rule its contacts with bodies that have none of their own.

Flexible bodies (`FLEX_SHAPES`): a ``cable`` is a rope of beam elements between two points, its ends
free, pinned in space or pinned to bodies (`CableSpec`). A core that cannot simulate one refuses it
when it is built, naming the feature and the core.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Sequence
from typing import Any

import numpy as np

from . import specs
from .bodies import joint_frames, joint_kind
from .errors import DynabrainError
from .module import Capabilities, Module, Port
from .specs import KEEP, MAKE_OTHERS, BodyInfo, BodySpec, Edits, Material, SceneSpec, Weld, quantities
from .suggest import did_you_mean

# the scene specs' home is `specs`; cores, scenarios and tests name these here too
COLORS, SHAPES, FLEX_SHAPES, JOINT_KINDS = specs.COLORS, specs.SHAPES, specs.FLEX_SHAPES, specs.JOINT_KINDS
CableSpec, JointSpec, NO_EDITS, scene_bodies = specs.CableSpec, specs.JointSpec, specs.NO_EDITS, specs.scene_bodies

WRENCH_UNIT = "N, N*m"
"""Unit of a body's wrench input: three forces, then three torques."""
VELOCITY_UNIT = "m/s, rad/s"
"""Unit of a body's velocity input: three linear velocities, then three angular ones."""


def body_inputs(free: Sequence[str]) -> tuple[Port, ...]:
    """The input ports a core gives its free bodies ``free`` (in body order): the blocks
    ``body_wrench`` and ``body_velocity`` (n, 6) and each body's row of them, ``B.wrench`` and
    ``B.velocity`` (see the module docstring); none when there is no free body. A core compares the
    velocity block's bytes with its start value's before each step: a tick where no brain writes it
    costs a bytes comparison."""
    if not free:
        return ()
    n, nan = len(free), float("nan")
    return (Port("body_wrench", (n, 6), WRENCH_UNIT, doc="force (N) and torque (N*m) on each free body, world "
                 "frame, at its centre of mass, held for the tick"),
            *(Port(f"{b}.wrench", (6,), WRENCH_UNIT, view_of=("body_wrench", i)) for i, b in enumerate(free)),
            Port("body_velocity", (n, 6), VELOCITY_UNIT, start=nan, doc="linear (m/s) and angular (rad/s) "
                 "velocity each free body takes at the start of each tick, world frame; NaN: left alone"),
            *(Port(f"{b}.velocity", (6,), VELOCITY_UNIT, view_of=("body_velocity", i), start=nan)
              for i, b in enumerate(free)))


def requested_velocity(request: np.ndarray, lin: np.ndarray, ang: np.ndarray
                       ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The linear and angular velocity (world frame) a body moving at ``lin``, ``ang`` takes from a
    velocity input ``request`` (6 values, NaN: left alone): each is None when its three requested
    components are all NaN (leave it untouched, bit for bit)."""
    out: list[np.ndarray | None] = []
    for want, now in ((request[:3], lin), (request[3:], ang)):
        keep = np.isnan(want)
        out.append(None if keep.all() else np.where(keep, now, want))
    return out[0], out[1]




class PhysicsCore(Module):
    """A physics engine as a module with a scene. Not feedthrough: outputs come from its state.

    An abstract class: a core implements every abstract method below (scene queries and structural
    edits), or it cannot be made (Python refuses to instantiate it, naming what is missing).
    Optional hooks have a default: `refresh_outputs`, `_check_param`.
    """

    CAPABILITIES = Capabilities(can_rollback=True, can_fork=True, feedthrough=False)
    ENGINE = "abstract"

    def __init__(self, name: str, scene: SceneSpec, **params):
        self.scene = scene
        super().__init__(name, **params)

    # -- scene queries ------------------------------------------------------------------------------
    @abstractmethod
    def objects(self) -> list[str]:
        """Names of the selectable objects: top-level bodies (each with its subtree)."""

    @abstractmethod
    def bodies(self) -> list[str]:
        """Names of every body."""

    @abstractmethod
    def joints(self) -> list[str]:
        """Names of every joint (hinge, slide, free) of the model."""

    @abstractmethod
    def body_info(self, name: str) -> BodyInfo:
        """Geometry and attachment of a body."""

    def engine_notes(self) -> str | None:
        """A line about what the engine said that was not shown (repeats of its warnings), for the end of
        a run; None by default."""
        return None

    def world_geoms(self) -> list[dict]:
        """Geoms that belong to no body (a model file's ground), each described as `BodyInfo.geoms` are,
        for drawing (logs, viewers); none by default."""
        return []

    def mesh(self, name: str) -> tuple[np.ndarray, np.ndarray] | None:
        """A model file's mesh ``name`` for drawing: vertices ``(n, 3)`` and faces ``(m, 3)``; None (left
        out of the drawing) by default."""
        return None

    @abstractmethod
    def body_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """World position (3,) and orientation quaternion (4, w-x-y-z) of a body, now."""

    @abstractmethod
    def body_velocity(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """World linear (3,) and angular (3,) velocity of a body, now."""

    # -- structural edits (part of the core's state) --------------------------------------------------
    @property
    @abstractmethod
    def selection(self) -> tuple[str, ...]:
        """The objects being simulated; the others are frozen where they stand (and still drawn), or absent."""

    @property
    def absent(self) -> tuple[str, ...]:
        """The objects out of the simulation (`make` with ``others="absent"``); none by default."""
        return ()

    @abstractmethod
    def make(self, objects: Sequence[str], others: str = "frozen") -> None:
        """Simulate only ``objects`` (the paper's d-make). ``others`` (`MAKE_OTHERS`) says what becomes of
        every other object: ``"frozen"`` keeps it where it stands as a static obstacle (its geometry stays:
        moving bodies collide with it, and an engine still pays a little per geom); ``"absent"`` takes it
        out of the simulation (no geometry, no contacts, nothing computed: the step costs what a scene of
        only the selected objects costs). Either way its output ports hold where it stood, and selecting
        it again later brings it back there, at rest; ports do not change, so connections stay. Static
        objects (a floor) are objects too: an absent floor holds nothing up. A joint made at run time
        (`make_joint`) between an object that would be absent and one that stays is refused, naming it."""

    @abstractmethod
    def make_joint(self, a: str, b: str, name: str | None = None, *, kind: str = "weld",
                   axis: Sequence[float] | None = None, anchor: Sequence[float] | None = None) -> str:
        """Join bodies ``a`` and ``b`` as they stand now; returns the joint's name. ``kind``: ``weld``
        (rigid), ``hinge`` (turns about ``axis`` through ``anchor``), ``slider`` (slides along
        ``axis``, keeping its orientation) or ``ball`` (turns about ``anchor``); ``axis`` and
        ``anchor`` are in the world frame (default: z, and b's origin). A core that cannot make a kind
        refuses it by name."""

    @abstractmethod
    def remove_joint(self, name: str) -> None:
        """Remove a joint made by `make_joint`."""

    @abstractmethod
    def no_collision(self, objects: Sequence[str]) -> None:
        """Turn off contacts among ``objects`` (pairwise, each with its subtree)."""

    @abstractmethod
    def place(self, body: str, pos: Sequence[float], quat: Sequence[float] | None = None) -> None:
        """Move a free body to a pose at rest (zero velocity)."""

    def refresh_outputs(self) -> None:
        """Rewrite every output from the current state. The world calls this after an edit that moves
        bodies between steps (`place`), so the bus shows the new pose before the next step. The
        default does nothing: right for a core whose edits write their outputs themselves."""

    # -- run-time bodies and materials (optional: the defaults refuse, naming the core) ----------------------
    def add_body(self, spec: BodySpec) -> None:
        """Add a top-level body where ``spec`` puts it, at rest. The core's ports change (the new
        body's outputs, and its inputs when it is free): the world reinstalls its structure."""
        raise DynabrainError(f"{self.ENGINE} core {self.name!r} cannot add bodies at run time")

    def remove_body(self, name: str) -> None:
        """Remove an object (a top-level body with what hangs on it), its run-time joints and collision
        filters with it. The core's ports change."""
        raise DynabrainError(f"{self.ENGINE} core {self.name!r} cannot remove bodies at run time")

    def set_material(self, body: str, *, friction: Any = KEEP, restitution: Any = KEEP, mass: Any = KEEP) -> None:
        """Give ``body`` its own friction, restitution or mass (None: the core's parameter again, the
        model's own mass); what is not given stays as it is. Contacts between a body with its own
        coefficients and one without take the body's own; see the core's docstring for two bodies with
        their own."""
        raise DynabrainError(f"{self.ENGINE} core {self.name!r} has no per-body friction, restitution or mass")

    def material(self, body: str) -> Material:
        """``body``'s own friction and restitution (None where it takes the core's)."""
        raise DynabrainError(f"{self.ENGINE} core {self.name!r} has no per-body friction or restitution")

    def ports_for_state(self, state: Any) -> tuple[tuple[Port, ...], tuple[Port, ...]] | None:
        """The (inputs, outputs) the core has in ``state`` (one of its `get_state` values), when they
        differ from its ports now (bodies added or removed); None when they do not, or it cannot say.
        `World.import_state` installs them, so that a state exported after `add_body` imports into a
        world built from the scenario alone."""
        return None

    # -- parameters ---------------------------------------------------------------------------------------
    def set_param(self, name: str, value: Any, *, running: bool = True) -> None:
        spec = self.param_specs().get(name)
        if spec is not None:  # refuse a bad value before it becomes the parameter's value
            self._check_param(name, spec.convert(value))
        super().set_param(name, value, running=running)

    def _check_param(self, name: str, value: Any) -> None:
        """Raise when ``value`` is out of range for parameter ``name`` (engines say which)."""


class EditedCore(PhysicsCore):
    """A physics core whose structural edits are one immutable value, part of its state:
    ``self._edits``, an `Edits` (frozen objects, joints made at run time, collision groups, bodies
    added and removed, per-body materials). The bookkeeping and the checks live here; an engine says
    how to freeze an object (`_freeze_entry`), what a weld holds (`_weld_data`), how to rebuild itself
    for an edits value (`_activate`, atomic: a value it cannot build raises and changes nothing) and
    how to write every output (`_write_all`). It keeps ``self._rows`` (body name -> row) and
    ``self._ports_in`` / ``self._ports_out``, and answers `objects`, `bodies`, `joints` from the
    engine's index of its scene (`_index`).

    Ports follow the bodies: an edits value with other bodies added or removed (`Edits.scene_key`)
    has other ports. The engine keeps one port layout per scene key it has seen, and when the world
    binds it with the ports of another layout (a rollback installs the structure of an earlier
    state, then restores the core's state), `bind` takes that layout (`_layout_for_binding`).
    """

    MADE_JOINTS: tuple[str, ...] = ("weld",)
    """The kinds of `make_joint` the engine makes (the others are refused, naming the kind)."""
    MASSES: bool = False
    """Whether the engine changes a body's mass at run time (`set_material(mass=...)`)."""

    _edits: Edits
    _rows: dict[str, int]
    _ports_in: tuple[Port, ...]
    _ports_out: tuple[Port, ...]

    # -- engine hooks --------------------------------------------------------------------------------
    @abstractmethod
    def _activate(self, edits: Edits, *, carry: bool) -> None:
        """Make ``edits`` the current structure, with the state carried over (``carry``) or not; a
        value the engine cannot build raises and changes nothing."""

    @abstractmethod
    def _write_all(self) -> None:
        """Write every output from the current state."""

    @property
    @abstractmethod
    def _index(self) -> Any:
        """The engine's index of its current scene: ``objects``, ``bodies`` and ``joints`` (names)."""

    def _edit(self, edits: Edits) -> None:
        """Make ``edits`` the current structure (state carried over) and write the outputs."""
        if edits != self._edits:
            self._activate(edits, carry=True)
            self._write_all()

    # -- the parts every engine shares ----------------------------------------------------------------
    def inputs(self) -> Sequence[Port]:
        return self._ports_in

    def outputs(self) -> Sequence[Port]:
        return self._ports_out

    def start(self, t_ns: int) -> None:
        self._write_all()

    def refresh_outputs(self) -> None:
        """Rewrite every output from the current state (the world calls this after `place`)."""
        self._write_all()

    def objects(self) -> list[str]:
        return list(self._index.objects)

    def bodies(self) -> list[str]:
        return list(self._index.bodies)

    def joints(self) -> list[str]:
        return list(self._index.joints)

    @abstractmethod
    def _freeze_entry(self, obj: str) -> tuple:
        """What freezing ``obj`` now must remember: an engine's NamedTuple whose first field,
        ``object``, is ``obj``."""

    @abstractmethod
    def _weld_data(self, a: str, b: str) -> tuple:
        """What a weld of ``b`` to ``a`` as they stand now must remember (`Weld.data`)."""

    @abstractmethod
    def _parent(self, body: str) -> str | None:
        """The parent body of ``body`` (None for a top-level object)."""

    def _reserved_joint_names(self) -> set[str]:
        """Names a joint made at run time may not take (besides the other made joints)."""
        return set(self.joints())

    def _body_spec(self, body: str) -> BodySpec | None:
        """The spec of a body of a primitive scene or added at run time; None for a model file's."""
        return None

    def _ports_of(self, edits: Edits) -> tuple[tuple[Port, ...], tuple[Port, ...]]:
        """The core's (inputs, outputs) with the bodies of ``edits`` (engines with run-time bodies say)."""
        return tuple(self.inputs()), tuple(self.outputs())

    def ports_for_state(self, state: Any) -> tuple[tuple[Port, ...], tuple[Port, ...]] | None:
        edits = state[0] if isinstance(state, tuple) and state and isinstance(state[0], Edits) else None
        if edits is None or edits.scene_key() == self._edits.scene_key():
            return None
        return self._ports_of(edits)

    def _scene_body(self, name: str) -> bool:
        """Whether ``name`` is an object of the scene's primitives (one `remove_body` may take out)."""
        return any(b.name == name for b in self.scene.bodies) and not self.scene.model

    # -- errors ----------------------------------------------------------------------------------------
    def fail(self, message: str) -> DynabrainError:
        return DynabrainError(f"{self.ENGINE} core {self.name!r}: {message}")

    def _unknown(self, kind: str, name: str, known: Sequence[str]) -> DynabrainError:
        listed = ", ".join(known[:12]) + (", ..." if len(known) > 12 else "") if known else "none"
        return self.fail(f"no {kind} {name!r}" + did_you_mean(str(name), known) + f"; {kind}s: {listed}")

    def _row(self, name: str) -> int:
        row = self._rows.get(name)
        if row is None:
            raise self._unknown("body", name, self.bodies())
        return row

    # -- the edits ---------------------------------------------------------------------------------------
    @property
    def selection(self) -> tuple[str, ...]:
        frozen = {entry.object for entry in self._edits.frozen}
        return tuple(o for o in self.objects() if o not in frozen)

    @property
    def absent(self) -> tuple[str, ...]:
        return self._edits.absent

    def make(self, objects: Sequence[str], others: str = "frozen") -> None:
        if others not in MAKE_OTHERS:
            raise self.fail(f"make(), field others: unknown mode {others!r}" + did_you_mean(str(others), MAKE_OTHERS)
                            + f"; one of: {', '.join(MAKE_OTHERS)}")
        chosen = self._objects(objects)
        kept = {entry.object: entry for entry in self._edits.frozen}
        entries = tuple(kept.get(o) or self._freeze_entry(o) for o in self.objects() if o not in chosen)
        absent = tuple(e.object for e in entries) if others == "absent" else ()
        if absent:
            self._check_absent(set(absent))
        self._edit(self._edits._replace(frozen=entries, absent=absent))

    def _check_absent(self, absent: set[str]) -> None:
        """Refuse a selection that would leave a joint made at run time with one side absent."""
        def top(body: str) -> str:
            while self._parent(body) is not None:
                body = self._parent(body)
            return body

        for w in self._edits.welds:
            gone = [top(b) in absent for b in (w.a, w.b)]
            if gone[0] != gone[1]:
                out, stays = (w.a, w.b) if gone[0] else (w.b, w.a)
                raise self.fail(f"make(), field others: 'absent' would take {top(out)!r} out of the simulation, "
                                f"but joint {w.name!r} (make_joint) holds it to {stays!r}, which stays; select both, "
                                "or remove_joint first")

    def _objects(self, objects: Sequence[str] | str) -> set[str]:
        known = self.objects()
        out = set()
        for o in [objects] if isinstance(objects, str) else objects:
            if o not in known:
                if o in self._rows:
                    top = o
                    while self._parent(top) is not None:
                        top = self._parent(top)
                    raise self.fail(f"{o!r} is not an object but a body of object {top!r}")
                raise self._unknown("object", o, known)
            out.add(o)
        return out

    def make_joint(self, a: str, b: str, name: str | None = None, *, kind: str = "weld",
                   axis: Sequence[float] | None = None, anchor: Sequence[float] | None = None) -> str:
        self._row(a)
        self._row(b)
        for body in (a, b) if self._edits.absent else ():
            top = body
            while self._parent(top) is not None:
                top = self._parent(top)
            if top in self._edits.absent:
                raise self.fail(f"make_joint({a!r}, {b!r}): {body!r} is out of the simulation (object {top!r} is "
                                "absent); select it with make() first")
        if a == b:
            raise self.fail(f"make_joint: a joint between a body and itself ({a!r}); it needs two different bodies")
        try:
            kind = joint_kind(kind)
        except DynabrainError as exc:
            raise self.fail(f"make_joint({a!r}, {b!r}), field kind: {exc}") from None
        if kind not in self.MADE_JOINTS:
            raise self.fail(f"make_joint({a!r}, {b!r}): the {self.ENGINE} core cannot make a {kind} joint "
                            f"(it makes: {', '.join(self.MADE_JOINTS)})")
        values = {}
        for key, given, dim in (("axis", axis, None), ("anchor", anchor, "length")):
            if given is None:
                continue
            if kind == "weld" or (kind == "ball" and key == "axis"):
                raise self.fail(f"make_joint({a!r}, {b!r}), field {key}: a {kind} joint takes no {key}")
            try:
                values[key] = np.array(quantities(given, 3, dim))
            except DynabrainError as exc:
                raise self.fail(f"make_joint({a!r}, {b!r}), field {key}: {exc}") from None
        if "axis" in values and not np.linalg.norm(values["axis"]) > 0:
            raise self.fail(f"make_joint({a!r}, {b!r}), field axis: the axis cannot be zero")
        name = name or f"joint_{a}_{b}"
        welds = self._edits.welds
        if name in {w.name for w in welds} | self._reserved_joint_names():
            raise self.fail(f"make_joint({a!r}, {b!r}), field name: a joint named {name!r} exists already")
        if kind == "weld":
            data = self._weld_data(a, b)
        else:
            pose_b = self.body_pose(b)
            data = joint_frames(self.body_pose(a), pose_b, values.get("anchor", pose_b[0]),
                                values.get("axis", (0.0, 0.0, 1.0)))
        self._edit(self._edits._replace(welds=(*welds, Weld(name, a, b, data, kind))))
        return name

    # -- bodies and materials at run time ---------------------------------------------------------------
    def add_body(self, spec: BodySpec) -> None:
        if not isinstance(spec, BodySpec):
            raise self.fail(f"add_body takes a BodySpec, got {type(spec).__name__}")
        if spec.name in self._rows or spec.name in self._reserved_joint_names():
            raise self.fail(f"add_body: body {spec.name!r}, field name: a body or joint named {spec.name!r} "
                            "exists already")
        if spec.parent is not None:
            raise self.fail(f"add_body: body {spec.name!r}, field parent: a body added at run time is top-level "
                            "(join it to another with make_joint)")
        self._edit(self._edits._replace(added=(*self._edits.added, spec)))

    def remove_body(self, name: str) -> None:
        objects = self.objects()
        if name not in objects:
            if name in self._rows:
                top = name
                while self._parent(top) is not None:
                    top = self._parent(top)
                raise self.fail(f"remove_body: {name!r} is not an object but a body of object {top!r}")
            raise self._unknown("object", name, objects)
        e = self._edits
        gone = set(self._subtree(name))
        if any(b.name == name for b in e.added):
            added, removed = tuple(b for b in e.added if b.name != name), e.removed
        elif self._scene_body(name):
            added, removed = e.added, (*e.removed, name)
        else:
            raise self.fail(f"remove_body: {name!r} comes from the model file; bodies added at run time and the "
                            "primitives of a scene can be removed")
        groups = tuple(g for g in (tuple(n for n in grp if n not in gone) for grp in e.groups) if len(g) > 1)
        self._edit(e._replace(
            added=added, removed=removed, groups=tuple(dict.fromkeys(groups)),
            frozen=tuple(f for f in e.frozen if f.object != name), absent=tuple(o for o in e.absent if o != name),
            welds=tuple(w for w in e.welds if w.a not in gone and w.b not in gone),
            materials=tuple(m for m in e.materials if m.body not in gone)))

    def _subtree(self, obj: str) -> list[str]:
        """``obj`` and every body under it."""
        out = [obj]
        for body in self.bodies():
            top = body
            while top is not None and top != obj:
                top = self._parent(top)
            if top == obj and body != obj:
                out.append(body)
        return out

    def material(self, body: str) -> Material:
        self._row(body)
        for m in self._edits.materials:
            if m.body == body:
                return m
        spec = self._body_spec(body)
        return Material(body, None if spec is None else spec.friction, None if spec is None else spec.restitution)

    def set_material(self, body: str, *, friction: Any = KEEP, restitution: Any = KEEP, mass: Any = KEEP) -> None:
        now = self.material(body)
        values = {"friction": now.friction, "restitution": now.restitution, "mass": now.mass}
        if mass is not KEEP and mass is not None and not self.MASSES:
            raise self.fail(f"set_material({body!r}), field mass: the {self.ENGINE} core does not change a body's "
                            "mass at run time")
        for key, given, high in (("friction", friction, None), ("restitution", restitution, 1.0), ("mass", mass, None)):
            if given is KEEP or given is None:
                values[key] = values[key] if given is KEEP else None
                continue
            try:
                x = float(given)
            except (TypeError, ValueError):
                raise self.fail(f"set_material({body!r}), field {key}: expected a number or None, "
                                f"got {given!r}") from None
            low_ok = x > 0 if key == "mass" else x >= 0
            if not (np.isfinite(x) and low_ok and (high is None or x <= high)):
                raise self.fail(f"set_material({body!r}), field {key}: {key} must be "
                                + ("above 0" if key == "mass" else "from 0")
                                + (f" to {high:g}" if high is not None else "") + f", got {given!r}")
            values[key] = x
        entry = Material(body, values["friction"], values["restitution"], values["mass"])
        kept = [m for m in self._edits.materials if m.body != body]
        spec = self._body_spec(body)
        if (spec is None or (spec.friction, spec.restitution) != (entry.friction, entry.restitution)
                or entry.mass is not None):
            kept.append(entry)
        self._edit(self._edits._replace(materials=tuple(sorted(kept, key=lambda m: m.body))))

    def remove_joint(self, name: str) -> None:
        welds = self._edits.welds
        made = [w.name for w in welds]
        if name not in made:
            if name in self.joints():
                raise self.fail(f"{name!r} is a joint of the scene; only joints made by make_joint can be removed")
            raise self._unknown("joint made by make_joint", name, made)
        self._edit(self._edits._replace(welds=tuple(w for w in welds if w.name != name)))

    def no_collision(self, objects: Sequence[str]) -> None:
        names: list[str] = []
        for o in [objects] if isinstance(objects, str) else objects:
            self._row(o)
            if o not in names:
                names.append(o)
        if len(names) < 2:
            raise self.fail(f"no_collision needs at least two objects, got {names}")
        groups = self._edits.groups
        group = tuple(sorted(names))
        if group not in groups:
            self._edit(self._edits._replace(groups=(*groups, group)))
