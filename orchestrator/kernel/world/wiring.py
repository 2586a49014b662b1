"""Wiring: modules added and removed, connections made and cut, loops declared for strong coupling,
and a core's ports laid out again after its bodies changed. Each edit builds a new `Structure` and
installs it (`Context.install`), values carried by name; history keeps the old one, so a rollback
installs it again. A failure leaves the world as it was."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from typing import Any

from .. import edits
from ..core import PhysicsCore
from ..errors import DynabrainError, WiringError
from ..iterate import LoopReport, LoopSpec, loops_without
from ..module import Module, SetupContext
from ..structure import Connection, ModuleRecord, build_structure, split_signal
from ..suggest import did_you_mean
from .context import Context
from .util import as_connection, call_module, close_quietly, module_spec


class Wiring:
    """The structure edits of one world (see the module docstring)."""

    def __init__(self, ctx: Context):
        self.ctx = ctx

    def add_module(self, module: Module, period: int | str | None,
                   connect: Iterable[Connection | Sequence[Any]]) -> None:
        ctx = self.ctx
        if not isinstance(module, Module):
            raise DynabrainError(f"add_module takes a Module, got {type(module).__name__}")
        if ctx.structure.record(module.name) is not None:
            raise WiringError(f"module name {module.name!r} is used twice")
        period_ns = ctx.period_ns(module, period)
        if isinstance(module, PhysicsCore) and ctx.core is not None:
            raise WiringError(f"world already has a physics core ({ctx.core.name!r})")
        self.setup(module, period_ns)
        try:
            record = ModuleRecord(module.name, module, period_ns // ctx.dt_ns,
                                  ctx.tick % (period_ns // ctx.dt_ns), period_ns,
                                  tuple(module.inputs()), tuple(module.outputs()))
            conns = [as_connection(c) for c in connect]
            new = build_structure((*ctx.structure.records, record), (*ctx.structure.connections, *conns),
                                  ctx.structure.loops)
        except BaseException:
            close_quietly(module)
            raise
        old = ctx.structure
        ctx.install(new, carry_values=True)
        try:
            module.bind()
            call_module(module, "start", ctx.tick, module.start, ctx.tick * ctx.dt_ns)
        except BaseException:
            ctx.install(old, carry_values=True)
            close_quietly(module)
            raise
        ctx.known[id(module)] = module
        if isinstance(module, PhysicsCore):
            ctx.core = module
        ctx.edited(edits.AddModule(module.name, module_spec(module, period_ns, conns)))

    def setup(self, module: Module, period_ns: int, *, importing: bool = False) -> None:
        """``module.setup`` with this world's context (its own random generator, the core); ``importing``:
        made for a state imported next (`SetupContext.importing`)."""
        ctx = self.ctx
        setup = SetupContext(ctx.name, ctx.dt_ns, period_ns, ctx.tick, ctx.rng_for(module.name),
                             module if isinstance(module, PhysicsCore) else ctx.core, importing=importing)
        call_module(module, "setup", ctx.tick, module.setup, setup)

    def remove_module(self, name: str) -> None:
        ctx = self.ctx
        rec = ctx.require_module(name)
        if rec.module is ctx.core:
            raise WiringError(f"the physics core {name!r} cannot be removed")
        records = [r for r in ctx.structure.records if r.name != name]
        conns = [c for c in ctx.structure.connections
                 if split_signal(c.src)[0] != name and split_signal(c.dst)[0] != name]
        ctx.install(build_structure(records, conns, loops_without(ctx.structure.loops, name)), carry_values=True)
        ctx.edited(edits.RemoveModule(name))

    def connect(self, src: str, dst: str, delay: bool) -> None:
        s = self.ctx.structure
        self.ctx.install(build_structure(s.records, (*s.connections, Connection(src, dst, delay)), s.loops),
                         carry_values=True)
        self.ctx.edited(edits.Connect(src, dst, delay))

    def disconnect(self, dst: str) -> None:
        s = self.ctx.structure
        if s.driver_of(dst) is None:
            raise WiringError(f"no connection drives {dst!r}")
        self.ctx.install(build_structure(s.records, [c for c in s.connections if c.dst != dst], s.loops),
                         carry_values=True)
        self.ctx.edited(edits.Disconnect(dst))

    def iterate(self, spec: LoopSpec) -> None:
        s = self.ctx.structure
        self.ctx.install(build_structure(s.records, s.connections, (*s.loops, spec)), carry_values=True)
        self.ctx.edited(edits.DeclareLoop(spec.name, spec.modules, spec.tolerance, spec.max_iterations))

    def loop_report(self, name: str) -> LoopReport | None:
        runners = self.ctx.structure.runners
        for runner in runners:
            if runner.spec.name == name:
                return runner.last
        raise WiringError(f"no loop {name!r}" + did_you_mean(name, [r.spec.name for r in runners]))

    def core_ports_changed(self) -> list[Connection]:
        """After a core edit that changed its ports (bodies added or removed), a structure with the
        core's new ports replaces the current one (values carried by name; connections to ports that
        are gone are dropped and returned). History keeps the old structure: a rollback installs it
        again, and the core takes the old ports back when it is bound to them."""
        ctx = self.ctx
        core = ctx.core
        assert core is not None
        rec = ctx.require_module(core.name)
        ins, outs = tuple(core.inputs()), tuple(core.outputs())
        if ins == rec.inputs and outs == rec.outputs:
            return []
        names = {f"{core.name}.{p.name}" for p in (*ins, *outs)}
        prefix = f"{core.name}."
        gone = [c for c in ctx.structure.connections
                if any(end.startswith(prefix) and end not in names for end in (c.src, c.dst))]
        records = [dataclasses.replace(r, inputs=ins, outputs=outs) if r is rec else r for r in ctx.structure.records]
        structure = build_structure(records, [c for c in ctx.structure.connections if c not in gone],
                                    ctx.structure.loops)
        ctx.install(structure, carry_values=True)
        core.refresh_outputs()
        ctx.dirty = True
        return gone
