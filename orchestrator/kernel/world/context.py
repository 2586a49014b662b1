"""A world's state as its parts share it (as Drake's Context is to its Simulator): the current
structure and the bus laid out for it, the tick, the core, history, the observers and the lock.

The parts (`stepper`, `timeline`, `wiring`, `scene`, `names`, `drive`, `transfer`, `realtime`) hold
one `Context` and change the world only through it; `World` is the face over them. `install` is the
one place a structure becomes current: the bus is laid out again and every module bound to it.
"""

from __future__ import annotations

import contextlib
import threading
import zlib
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core import PhysicsCore
from ..edits import Edit
from ..errors import DynabrainError, WiringError, WorldClosedError
from ..history import History
from ..module import Module
from ..observers import Observer, WorldEvent, WorldView
from ..structure import ModuleRecord, Structure, build_structure
from ..suggest import did_you_mean
from ..units import format_duration, parse_duration_ns
from .util import close_quietly, nothing, read_only

if TYPE_CHECKING:
    from .facade import World

ScheduledAction = Callable[["World"], None]


class Context:
    """The state every part of one world reads and writes (see the module docstring). Attributes, not
    properties: the tick's hot path reads them."""

    def __init__(self, name: str, dt_ns: int, seed: int, history: History, compiled: bool,
                 module_factory: Callable[[dict[str, Any]], Module] | None,
                 rebuild: Callable[[], World] | None):
        self.name, self.dt_ns, self.seed, self.compiled = name, dt_ns, seed, compiled
        self.lock = threading.RLock()
        self.open = _Open(self)  # ``with ctx.open:`` the lock, held on a world that is open
        self.history = history
        self.structure = build_structure((), ())
        self.buf = np.zeros(0)
        self.mv = memoryview(self.buf)  # the bus again: the tick's copies are cheaper on it
        self.ro = read_only(self.buf)  # and read-only, for observers
        self.run_tick: Callable[[int, int], None] = nothing  # the structure's tick on this bus (`CompiledTick.bind`)
        self.tick = 0
        self.dirty = True  # edited since the current tick's state was saved: the next tick saves it again
        self.closed = False
        self.core: PhysicsCore | None = None
        self.observers: list[Observer] = []
        self.world: World | None = None  # set by the World: what scheduled actions are handed
        self.view: WorldView | None = None  # ... and what observers are
        self.scheduled: dict[int, list[tuple[str, ScheduledAction]]] = {}
        self.known: dict[int, Module] = {}  # every module ever set up here, closed at close()
        self.source = "api"  # who is editing: "scenario" while scheduled actions run
        self.id = id(self)
        self.error: BaseException | None = None
        self.module_factory = module_factory
        self.rebuild = rebuild
        # what `Timeline.capture` saves, made again after a change of structure or parameters or a restore:
        self.params: tuple[dict[str, Any], ...] = ()  # every module's parameter dict, shared by states
        self.save_states: Callable[[], tuple] = tuple  # every module's state, in one call
        self.record: Callable[[int], None] = nothing  # history's entry of a tick, in one call (`state_saver`)
        self.saver_of: Structure | None = None  # ... for this structure; None once a parameter changed
        # (the modules' bindings tell `param_changed`) or a state was restored

    # -- events ---------------------------------------------------------------------------------------
    def emit(self, kind: str, /, **detail: Any) -> None:
        if not self.observers:
            return
        event = WorldEvent(self.tick, kind, detail, self.source)
        for obs in self.observers:
            obs.on_event(self.view, event)

    def edited(self, edit: Edit) -> None:
        """An edit at this tick: part of the tick's state (saved again before the next step), and told."""
        self.dirty = True
        self.tell(edit)

    def tell(self, edit: Edit) -> None:
        """Tell the observers of an edit (a `WorldEvent` with its record and its detail)."""
        if self.observers:
            event = WorldEvent(self.tick, edit.kind, edit.detail(), self.source, edit)
            for obs in self.observers:
                obs.on_event(self.view, event)

    def rolled_back(self, from_tick: int) -> None:
        for obs in self.observers:
            obs.on_rollback(self.view, from_tick)

    def close(self) -> None:
        """Tell observers, close every module this world set up, drop history (`World.close`)."""
        if self.closed:
            return
        for obs in list(self.observers):
            with contextlib.suppress(Exception):
                obs.on_close(self.view)
        self.closed = True
        for module in self.known.values():
            close_quietly(module)
        self.known.clear()
        self.history.clear()

    # -- checks ---------------------------------------------------------------------------------------
    def check_open(self) -> None:
        if self.closed:
            raise WorldClosedError(f"world {self.name!r} is closed")

    def require_module(self, name: str) -> ModuleRecord:
        rec = self.structure.record(name)
        if rec is None:
            raise WiringError(f"no module {name!r}" + did_you_mean(name, self.structure.names))
        return rec

    def require_core(self, call: str) -> PhysicsCore:
        self.check_open()
        if self.core is None:
            raise DynabrainError(f"{call}() needs a physics core, and this world has none")
        return self.core

    def period_ns(self, module: Module, period: int | str | None) -> int:
        value = period if period is not None else module.DEFAULT_PERIOD
        ns = self.dt_ns if value is None else (value if isinstance(value, int) else parse_duration_ns(value))
        if ns <= 0 or ns % self.dt_ns:
            raise WiringError(f"module {module.name!r}: period {format_duration(ns)} is not a whole multiple "
                              f"of the base step {format_duration(self.dt_ns)}")
        return ns

    def rng_for(self, name: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, zlib.crc32(name.encode())])

    # -- the structure and its bus --------------------------------------------------------------------
    def param_changed(self, module: Module) -> None:
        """A module bound here changed a parameter (`PortBinding.param_changed`): the states saved from
        now on hold its new parameter dict (and the state of a module whose steps leave it alone is
        taken again: `on_param` may have changed it)."""
        self.saver_of = None

    def install(self, structure: Structure, *, carry_values: bool, bus: np.ndarray | None = None) -> None:
        """Make ``structure`` current: allocate the bus, carry values by name, rebind modules (each
        gets a `PortBinding` of the new bus through `Module.bind_ports`, then `bind` is called).
        ``bus``: the values the new bus starts with (a fork's: its world's bus, laid out the same);
        without it, the ports' start values (new ports begin there) and what is carried."""
        buf = structure.layout.new_bus() if bus is None else bus.copy()
        if carry_values:
            self._carry(structure, buf)
        self.buf, self.mv, self.ro = buf, memoryview(buf), read_only(buf)
        self.structure = structure
        self.run_tick = (structure.compiled if self.compiled else structure.plain).bind(self.mv, buf)
        self.saver_of = None  # `record` copies the old bus
        for rec in structure.records:
            rec.module.bind_ports(structure.layout.modules[rec.name].binding(buf, self.ro, self.param_changed))
            rec.module.bind()
        for runner in structure.runners:  # iterate (issue 28): a loop's runner steps its members on this bus
            runner.bind(buf, self.emit)

    def _carry(self, structure: Structure, buf: np.ndarray) -> None:
        """The current bus's values into ``buf`` (laid out for ``structure``), by signal name."""
        old_layout, old_buf = self.structure.layout, self.buf
        resized: set[str] = set()  # blocks whose size changed (a core's, after add_body): carry their views
        for name, slot in structure.layout.slots.items():
            if slot.port.view_of is None:
                old = old_layout.slots.get(name)
                if old is not None and old.size == slot.size:
                    buf[slot.start:slot.start + slot.size] = old_buf[old.start:old.start + old.size]
                elif old is not None:
                    resized.add(name)
        for name, slot in structure.layout.slots.items() if resized else ():
            old = old_layout.slots.get(name)
            if (old is not None and old.size == slot.size and slot.port.view_of is not None
                    and f"{name.partition('.')[0]}.{slot.port.view_of[0]}" in resized):
                buf[slot.start:slot.start + slot.size] = old_buf[old.start:old.start + old.size]


class _Open:
    """``with ctx.open:``: take the world lock, and raise `WorldClosedError` (the lock let go) when the
    world is closed."""

    __slots__ = ("ctx",)

    def __init__(self, ctx: Context):
        self.ctx = ctx

    def __enter__(self) -> None:
        self.ctx.lock.acquire()
        if self.ctx.closed:
            self.ctx.lock.release()
            self.ctx.check_open()

    def __exit__(self, *exc: object) -> None:
        self.ctx.lock.release()
