"""Scene edits, delegated to the physics core and part of its state (so of history and forks): the
objects simulated (`make`), joints made and removed, bodies added and removed while the world runs,
per-body materials, collision filters and placing a body. A bad name or value raises naming the call
and the field, and the world is left as it was."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

from .. import edits
from ..core import MAKE_OTHERS, BodySpec, PhysicsCore
from ..errors import DynabrainError
from ..specs import BodySpecError
from ..structure import Connection
from ..suggest import did_you_mean
from .context import Context
from .util import expand_names, names_of, world_values
from .wiring import Wiring

MATERIAL_KEYS = ("friction", "restitution", "mass")


class SceneEdits:
    """The scene edits of one world (see the module docstring). The caller holds the world lock; each
    edit checks that the world is open and has a core (`Context.require_core`)."""

    def __init__(self, ctx: Context, wiring: Wiring):
        self.ctx = ctx
        self.wiring = wiring

    def make(self, objects: Iterable[str] | str, others: str) -> None:
        core = self.ctx.require_core("make")
        if others not in MAKE_OTHERS:
            raise DynabrainError(f"make(), field others: unknown mode {others!r}"
                                 + did_you_mean(str(others), MAKE_OTHERS) + f"; one of: {', '.join(MAKE_OTHERS)}")
        names = expand_names(names_of(objects), core.objects(), "object", "make")
        if others == "frozen":
            core.make(names)  # (a core of another author may not take ``others``)
        else:
            core.make(names, others)
        self.ctx.edited(edits.Make(tuple(names), others))

    def make_joint(self, a: str, b: str, name: str | None, kind: str, axis: Sequence[Any] | None,
                   anchor: Sequence[Any] | None) -> str:
        core = self.ctx.require_core("make_joint")
        expand_names([a, b], core.bodies(), "body", "make_joint")
        extra = {k: v for k, v in (("axis", axis), ("anchor", anchor)) if v is not None}
        joint = core.make_joint(a, b, name, kind=kind, **extra) if extra or kind != "weld" else \
            core.make_joint(a, b, name)
        si = {k: tuple(world_values(v, k)) for k, v in extra.items()}
        self.ctx.edited(edits.MakeJoint(a, b, joint, kind, si.get("axis"), si.get("anchor")))
        return joint

    def remove_joint(self, name: str) -> None:
        self.ctx.require_core("remove_joint").remove_joint(name)
        self.ctx.edited(edits.RemoveJoint(name))

    # -- bodies at run time (the core's ports change: the structure is installed again) -----------------
    def add_body(self, spec: BodySpec | None, fields: dict[str, Any]) -> str:
        core = self.ctx.require_core("add_body")
        try:
            spec = spec if isinstance(spec, BodySpec) and not fields else BodySpec(**fields)
        except BodySpecError as exc:
            raise BodySpecError(exc.body, exc.field, exc.detail, call="add_body") from None
        except TypeError as exc:
            raise DynabrainError(f"add_body(): {exc} (a BodySpec, or its fields by name: name, shape, size, "
                                 "pos, quat, mass, color, joint, friction, restitution, mesh, scale)") from None
        self._edit_bodies(core, lambda: core.add_body(spec))
        self.ctx.edited(edits.AddBody(spec))
        return spec.name

    def remove_body(self, name: str) -> None:
        core = self.ctx.require_core("remove_body")
        dropped = self._edit_bodies(core, lambda: core.remove_body(name))
        self.ctx.edited(edits.RemoveBody(name, tuple(str(c) for c in dropped)))

    def _edit_bodies(self, core: PhysicsCore, edit: Callable[[], None]) -> list[Connection]:
        """Make a core edit that changes the core's ports, then install a structure with its new ports
        (`Wiring.core_ports_changed`); when that fails the core goes back to its state before."""
        before = core.get_state()
        edit()
        try:
            return self.wiring.core_ports_changed()
        except BaseException:
            core.set_state(before)
            raise

    # -- per-body materials, contacts, poses ------------------------------------------------------------
    def set_material(self, body: str, **values: Any) -> None:
        core = self.ctx.require_core("set_material")
        expand_names([body], core.bodies(), "body", "set_material")
        core.set_material(body, **values)
        m = core.material(body)
        self.ctx.edited(edits.SetMaterial(body, m.friction, m.restitution, m.mass))

    def material_target(self, name: str) -> tuple[str, str] | None:
        """(body, ``friction``, ``restitution`` or ``mass``) when ``name`` is ``<core>.<body>.friction``,
        ``.restitution`` or ``.mass`` (or without the core's name) of a body of the core, else None."""
        core = self.ctx.core
        if core is None:
            return None
        rest = name[len(core.name) + 1:] if name.startswith(f"{core.name}.") else name
        body, _, key = rest.rpartition(".")
        if key in MATERIAL_KEYS and body in core.bodies():
            return body, key
        return None

    def no_collision(self, objects: Iterable[str] | str) -> None:
        core = self.ctx.require_core("no_collision")
        names = expand_names(names_of(objects), core.bodies(), "body", "no_collision")
        core.no_collision(names)
        self.ctx.edited(edits.NoCollision(tuple(names)))

    def place(self, body: str, pos: Sequence[float], quat: Sequence[float] | None) -> None:
        core = self.ctx.require_core("place")
        expand_names([body], core.bodies(), "body", "place")
        core.place(body, pos, quat)
        core.refresh_outputs()
        self.ctx.edited(edits.Place(body, tuple(map(float, pos)), None if quat is None else tuple(map(float, quat))))
