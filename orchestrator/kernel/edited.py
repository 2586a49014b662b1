"""A physics core whose structural edits are one immutable value, part of its state (`EditedCore`): the
bookkeeping and the checks of `make`, `make_joint`, `no_collision`, `add_body`, `remove_body` and
`set_material` that both engines share, and the ports that follow the bodies. See `kernel.core` for the
interface and its words.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Sequence
from typing import Any

import numpy as np

from .bodies import joint_frames, joint_kind
from .core import PhysicsCore
from .errors import DynabrainError
from .module import Port
from .specs import KEEP, MAKE_OTHERS, BodySpec, Edits, Material, Weld, quantities
from .suggest import did_you_mean


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
