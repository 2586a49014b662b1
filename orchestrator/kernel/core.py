"""The physics-core interface, engine-neutral, and the scene of primitives both cores build.

A physics core is a Module with a scene. The kernel speaks only these words; the MuJoCo and Exudyn
cores translate them to their engines. Structural edits (`make`, `make_joint`, `no_collision`,
`add_body`, `remove_body`, `set_material`) and run-time parameter changes are part of the core's
state, so history and rollback restore them.

The ports follow the bodies: every body present has its ports, so `add_body` and `remove_body` change
the core's `inputs` and `outputs`. The world then installs a structure with the new ports (values
carried by name, connections to ports that are gone dropped); history keeps the old structure, and
when a rollback installs it the core is bound to the old ports, which it takes back by their names
(`kernel.edited.EditedCore`). `ports_for_state` tells an importing world the ports of an exported state.

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
from .errors import DynabrainError
from .module import Capabilities, Module, Port
from .specs import KEEP, BodyInfo, BodySpec, Material, SceneSpec

# the scene specs' home is `specs`; cores, scenarios and tests name these here too
COLORS, SHAPES, FLEX_SHAPES, JOINT_KINDS = specs.COLORS, specs.SHAPES, specs.FLEX_SHAPES, specs.JOINT_KINDS
CableSpec, JointSpec, NO_EDITS, scene_bodies = specs.CableSpec, specs.JointSpec, specs.NO_EDITS, specs.scene_bodies
MAKE_OTHERS, Edits, Weld = specs.MAKE_OTHERS, specs.Edits, specs.Weld

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
