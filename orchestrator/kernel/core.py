"""The physics-core interface, engine-neutral, and the scene of primitives both cores build.

A physics core is a Module with a scene. The kernel speaks only these words; the MuJoCo and Exudyn
cores translate them to their engines. Structural edits (`make`, `make_joint`, `no_collision`) and
run-time parameter changes are part of the core's state, so history and rollback restore them.

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
it), ``gravity`` (3-vector, m/s^2), ``substeps`` (engine steps per module step).

Flexible bodies (`FLEX_SHAPES`): a ``cable`` is a rope of beam elements between two points, its ends
free, pinned in space or pinned to bodies (`CableSpec`). A core that cannot simulate one refuses it
when it is built, naming the feature and the core.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from .errors import DynabrainError
from .module import Capabilities, Module, Port
from .portable import state_type
from .suggest import did_you_mean

SHAPES = ("plane", "box", "sphere", "capsule", "cylinder")
FLEX_SHAPES = ("cable",)
"""Shapes of flexible bodies (not every core has them; see `CableSpec`)."""
JOINT_KINDS = ("free", "hinge", "slide", "fixed")

COLORS: dict[str, tuple[float, float, float, float]] = {
    "red": (0.85, 0.15, 0.15, 1.0),
    "green": (0.2, 0.7, 0.25, 1.0),
    "blue": (0.15, 0.3, 0.85, 1.0),
    "yellow": (0.95, 0.85, 0.1, 1.0),
    "orange": (0.95, 0.55, 0.1, 1.0),
    "purple": (0.55, 0.25, 0.75, 1.0),
    "cyan": (0.1, 0.75, 0.85, 1.0),
    "magenta": (0.85, 0.2, 0.7, 1.0),
    "white": (0.95, 0.95, 0.95, 1.0),
    "grey": (0.5, 0.5, 0.5, 1.0),
    "gray": (0.5, 0.5, 0.5, 1.0),
    "black": (0.08, 0.08, 0.08, 1.0),
    "brown": (0.5, 0.3, 0.15, 1.0),
}


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


@dataclass(frozen=True)
class JointSpec:
    """How a body is attached to its parent (the world when it has none).

    ``axis`` is in the body frame; ``anchor`` is the joint's position in the body frame.
    ``range`` limits a hinge (rad) or slide (m).
    """

    kind: str = "free"
    name: str | None = None
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    anchor: tuple[float, float, float] = (0.0, 0.0, 0.0)
    range: tuple[float, float] | None = None
    damping: float = 0.0


@dataclass(frozen=True)
class CableSpec:
    """What a ``cable`` body has beyond a `BodySpec`: a rope, straight at t=0 from the body's ``pos``
    (world frame) to ``end``, of ``segments`` beam elements.

    ``axial_stiffness`` is EA (N: the force that would double its length), ``bending_stiffness`` EI
    (N*m^2), ``damping`` a time constant (s): the axial and bending damping are ``damping`` times the
    stiffnesses. ``attach`` says what holds each end (start, end): None for a free end, ``"world"``
    to pin it where it is, or a body's name to pin it to that body at the point where it is at t=0.
    The body's ``size`` is ``(radius,)`` and its ``mass`` the whole cable's.
    """

    end: tuple[float, float, float]
    segments: int = 8
    axial_stiffness: float = 1.0e4
    bending_stiffness: float = 1.0e-3
    damping: float = 0.0
    attach: tuple[str | None, str | None] = (None, None)


@dataclass(frozen=True)
class BodySpec:
    """One primitive body of a scene.

    ``size`` by shape: box: full edge lengths (x, y, z); sphere: (radius,); capsule and cylinder:
    (radius, length along the body z axis); plane: (half-x, half-y) or () for infinite; cable:
    (radius,), with the rest in ``cable``.
    ``pos`` is in the parent's frame (the world's when ``parent`` is None); ``quat`` is w-x-y-z.
    A plane is always static; a top-level body without ``joint`` is free.
    """

    name: str
    shape: str
    size: tuple[float, ...]
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    mass: float | None = None
    color: tuple[float, float, float, float] = COLORS["grey"]
    joint: JointSpec | None = None
    parent: str | None = None
    friction: float | None = None
    line: int | None = None
    """Line in the scenario file where the body is written (for errors)."""
    cable: CableSpec | None = None
    """The rope of a ``cable`` body (shape in `FLEX_SHAPES`); None for rigid shapes."""


@dataclass(frozen=True)
class SceneSpec:
    """A scene: primitives, or an engine model file (``model``), plus options."""

    bodies: tuple[BodySpec, ...] = ()
    model: str | None = None
    """Path of an engine model file (MJCF for MuJoCo), resolved against the scenario's folder."""
    options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class BodyInfo:
    """What a core tells about one body (for viewers, logs and expectation expressions)."""

    name: str
    free: bool
    parent: str | None
    geoms: tuple[dict, ...] = ()


@state_type
class Weld(NamedTuple):
    """A joint made at run time (`PhysicsCore.make_joint`): body ``b`` held rigidly to body ``a`` as
    they stood when it was made."""

    name: str
    """The joint's name (unique among the scene's joints and the other welds)."""
    a: str
    b: str
    data: tuple
    """What the engine needs to make the weld again (the relative pose, in the engine's terms)."""


@state_type
class Edits(NamedTuple):
    """The structural edits of an `EditedCore`, as one immutable, hashable value (part of its state:
    history keeps it, a restore compares it, a core caches what it compiled for it)."""

    frozen: tuple = ()
    """One engine-made entry per frozen object, a NamedTuple whose first field, ``object``, is the
    object's name (the rest: where its bodies and joints stood when it froze)."""
    welds: tuple[Weld, ...] = ()
    """The joints made at run time, in the order they were made."""
    groups: tuple[tuple[str, ...], ...] = ()
    """The objects of each `no_collision`, sorted, in the order the calls came."""


NO_EDITS = Edits()
"""The structure of a scene as it was written: nothing frozen, no weld, no collision filter."""


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
        """The objects being simulated; the others are frozen where they stand (and still drawn)."""

    @abstractmethod
    def make(self, objects: Sequence[str]) -> None:
        """Simulate only ``objects``; freeze every other object at its current pose."""

    @abstractmethod
    def make_joint(self, a: str, b: str, name: str | None = None) -> str:
        """Join bodies ``a`` and ``b`` rigidly as they stand now; returns the joint's name."""

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
    ``self._edits``, an `Edits` (frozen objects, welds, collision groups). The bookkeeping and the
    checks live here; an engine says how to freeze an object (`_freeze_entry`), what a weld holds
    (`_weld_data`) and how to rebuild itself for an edits value (`_edit`). It keeps ``self._rows``
    (body name -> row) and answers `objects`, `bodies`, `joints`.
    """

    _edits: Edits
    _rows: dict[str, int]

    # -- engine hooks --------------------------------------------------------------------------------
    @abstractmethod
    def _edit(self, edits: Edits) -> None:
        """Make ``edits`` the current structure (state carried over)."""

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

    def make(self, objects: Sequence[str]) -> None:
        chosen = self._objects(objects)
        kept = {entry.object: entry for entry in self._edits.frozen}
        entries = tuple(kept.get(o) or self._freeze_entry(o) for o in self.objects() if o not in chosen)
        self._edit(self._edits._replace(frozen=entries))

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

    def make_joint(self, a: str, b: str, name: str | None = None) -> str:
        self._row(a)
        self._row(b)
        if a == b:
            raise self.fail(f"make_joint needs two different bodies, got {a!r} twice")
        name = name or f"joint_{a}_{b}"
        welds = self._edits.welds
        if name in {w.name for w in welds} | self._reserved_joint_names():
            raise self.fail(f"a joint named {name!r} exists already")
        self._edit(self._edits._replace(welds=(*welds, Weld(name, a, b, self._weld_data(a, b)))))
        return name

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
