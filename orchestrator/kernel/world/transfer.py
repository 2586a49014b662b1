"""Portable state: a world's state as versioned bytes (`kernel.portable` lays them out) and back, in this
world or in another built the same way (another process, another host). Importing a state whose
modules differ makes the missing ones with the world's ``module_factory`` and drops the extra ones;
anything that does not match is refused with the world unchanged."""

from __future__ import annotations

from typing import Any

from .. import portable
from ..core import PhysicsCore
from ..errors import RollbackError
from ..history import WorldState
from ..module import Module
from ..structure import Connection, ModuleRecord, Structure, build_structure
from ..units import format_duration
from .context import Context
from .timeline import Timeline
from .util import close_quietly, module_spec, same_params
from .wiring import Wiring


def _class_path(module: Module) -> str:
    return f"{type(module).__module__}:{type(module).__qualname__}"


class StateTransfer:
    """Export and import of one world's state (see the module docstring). The caller holds the lock."""

    def __init__(self, ctx: Context, timeline: Timeline, wiring: Wiring):
        self.ctx = ctx
        self.timeline = timeline
        self.wiring = wiring
        self._heads: dict[tuple[int, int], tuple] = {}  # export's headers (`_header`)
        self._signatures: dict[int, tuple[ModuleRecord, str]] = {}  # `_signature_of`

    def export(self, snapshot: WorldState | None) -> bytes:
        state = self.timeline.capture() if snapshot is None else snapshot
        if not isinstance(state, WorldState) or state.world_id != self.ctx.id:
            raise RollbackError("export_state() takes a snapshot made by this same world")
        self.timeline.check_restorable(state, "export_state")
        records = state.structure.records
        return portable.encode(self._header(state), state.bus, state.states, state.params, lambda i: records[i].name)

    def _header(self, state: WorldState) -> dict[str, Any]:
        """The header's fields but the tick: made once per structure and set of parameter dicts (the
        cache holds them, so their ids stay theirs)."""
        key = (id(state.structure), id(state.params))
        hit = self._heads.get(key)
        if hit is None or hit[0] is not state.structure or hit[1] is not state.params:
            modules = [{"name": r.name, "class": _class_path(r.module), "signature": self._signature_of(r),
                        "period_ns": r.period_ns, "phase": r.phase,
                        "spec": module_spec(r.module, r.period_ns)} for r in state.structure.records]
            conns = [[c.src, c.dst, c.delay] for c in state.structure.connections]
            head = {"world": self.ctx.name, "step_ns": self.ctx.dt_ns, "modules": modules, "connections": conns,
                    "bus": int(state.bus.size)}
            if len(self._heads) >= 8:
                self._heads.clear()
            hit = self._heads[key] = (state.structure, state.params, head)
        return {**hit[2], "tick": state.tick}

    def import_(self, data: bytes) -> None:
        ps = self.decode(data)
        structure = self._structure_for(ps)
        params = tuple(same_params(rec.module.param_state(), values)
                       for rec, values in zip(structure.records, ps.params, strict=True))
        state = WorldState(self.ctx.id, ps.tick, structure, ps.bus, ps.states, params)
        self.timeline.restore(state, snapshot=0, imported=True)

    def decode(self, data: bytes) -> portable.PortableState:
        """The state in ``data``, checked against this world (`World.check_state`)."""
        ps = portable.decode(data)
        if ps.step_ns != self.ctx.dt_ns:
            raise portable.StateFormatError(
                f"import_state: the state is of a world with step {format_duration(ps.step_ns)} (world "
                f"{ps.world!r}); this world's step is {format_duration(self.ctx.dt_ns)}")
        mine = {rec.name: rec for rec in self.ctx.structure.records}
        for entry, saved in zip(ps.modules, ps.states, strict=True):
            rec = mine.get(entry.name)
            if rec is None:
                continue
            cls = _class_path(rec.module)
            if cls != entry.cls or (self._signature_of(rec) != entry.signature
                                    and self._ports_in_state(rec.module, entry, saved) is None):
                raise portable.StateFormatError(
                    f"import_state: module {entry.name!r} differs: the state's (world {ps.world!r}) is {entry.cls}, "
                    f"this world's is {cls}" + (" with other ports (another scene or configuration?)"
                                                 if cls == entry.cls else ""))
        return ps

    def _signature_of(self, rec: ModuleRecord) -> str:
        """`portable.signature` of a module as present here, kept per record (records live as long as
        their structure)."""
        hit = self._signatures.get(id(rec))
        if hit is None or hit[0] is not rec:
            if len(self._signatures) > 4096:
                self._signatures.clear()
            hit = self._signatures[id(rec)] = (rec, portable.signature(rec.module, (*rec.inputs, *rec.outputs)))
        return hit[1]

    def _ports_in_state(self, module: Module, entry: portable.ModuleEntry, saved: Any) -> tuple | None:
        """(inputs, outputs) of a core whose ports in the state differ from its ports here (bodies added
        or removed: `PhysicsCore.ports_for_state`), when they are the state's; else None."""
        ports = module.ports_for_state(saved) if isinstance(module, PhysicsCore) else None
        if ports is None or portable.signature(module, (*ports[0], *ports[1])) != entry.signature:
            return None
        return ports

    def _structure_for(self, ps: portable.PortableState) -> Structure:
        """This world's structure when it matches the state's, else one made for it (new modules made
        and set up; a failure closes them and leaves the world as it was)."""
        ctx = self.ctx
        current = ctx.structure
        present = {r.name: r for r in current.records}
        other_ports = {}  # a core with other bodies in the state: its ports there (`decode` checked them)
        for entry, saved in zip(ps.modules, ps.states, strict=True):
            rec = present.get(entry.name)
            if rec is not None and self._signature_of(rec) != entry.signature:
                other_ports[entry.name] = self._ports_in_state(rec.module, entry, saved)
        if not other_ports and (len(ps.modules) == len(current.records) and ps.connections == tuple(
                (c.src, c.dst, c.delay) for c in current.connections) and all(
                e.name == r.name and e.period_ns == r.period_ns and e.phase == r.phase
                for e, r in zip(ps.modules, current.records, strict=True))):
            return current  # the usual case (`decode` has checked the modules)
        by_name: dict[str, ModuleRecord | Module] = {m.name: m for m in ctx.known.values()}  # removed ones too
        by_name.update({rec.name: rec for rec in current.records})
        made: list[Module] = []
        records: list[ModuleRecord] = []
        try:
            for entry in ps.modules:
                have = by_name.get(entry.name)
                if isinstance(have, ModuleRecord):  # present: checked by `decode`
                    module, inputs, outputs = have.module, have.inputs, have.outputs
                    if other_ports.get(entry.name) is not None:  # a core with other bodies in the state
                        inputs, outputs = other_ports[entry.name]
                else:
                    module = have if have is not None else self._make_for_import(entry, made)
                    inputs, outputs = tuple(module.inputs()), tuple(module.outputs())
                    cls = _class_path(module)
                    if cls != entry.cls or portable.signature(module, (*inputs, *outputs)) != entry.signature:
                        raise portable.StateFormatError(
                            f"import_state: module {entry.name!r} differs: the state's is {entry.cls}, this world's "
                            f"is {cls}" + (" with other ports (another scene or configuration?)"
                                           if cls == entry.cls else ""))
                records.append(ModuleRecord(entry.name, module, entry.period_ns // ctx.dt_ns, entry.phase,
                                            entry.period_ns, inputs, outputs))
            structure = build_structure(records, [Connection(s, d, x) for s, d, x in ps.connections],
                                        current.loops)  # (loops: this world's, built the same way)
        except BaseException:
            for module in made:
                close_quietly(module)
                ctx.known.pop(id(module), None)
            raise
        return structure

    def _make_for_import(self, entry: portable.ModuleEntry, made: list[Module]) -> Module:
        ctx = self.ctx
        if ctx.module_factory is None:
            raise portable.StateFormatError(
                f"import_state: the state has module {entry.name!r} ({entry.cls}), which this world lacks, and the "
                "world has no module_factory to make it (a world from load_world has one)")
        module = ctx.module_factory(entry.spec)
        made.append(module)
        ctx.known[id(module)] = module
        self.wiring.setup(module, entry.period_ns, importing=True)
        return module
