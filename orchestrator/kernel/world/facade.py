"""The World: the brain's class (after EusDyna's d-* calls), a face over named parts.

Each public method takes the world lock, checks its arguments and hands the work to one part:
`Stepper` (ticks and events), `Timeline` (history, snapshots, rollback, fork), `Wiring` (modules and
connections), `SceneEdits` (the core's scene), `Names` (get and set by name), `Drive` (driven runs,
imagined futures), `StateTransfer` (portable state) and `RealtimeRunner` (the loop in a thread), made
together (`Parts`) over one `Context`. Any method may be called from another thread while `start()` runs the loop;
``with world.lock:`` groups several calls so the loop cannot step between them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from ..compiled import compiled_by_default
from ..core import KEEP, BodySpec, PhysicsCore, SceneSpec
from ..errors import DynabrainError, RollbackError
from ..history import History, WorldState
from ..iterate import LoopReport, LoopSpec
from ..module import Module
from ..observers import Imagined, Observer, WorldView
from ..plugins import resolve_core
from ..structure import Connection
from ..units import NS_PER_S, parse_duration_ns
from .context import Context, ScheduledAction
from .parts import Parts
from .util import Lock

FLOOR_HALF_M = 2.0
"""Half the side of the floor a world made with an engine's name stands on."""
KEYFRAME_EVERY = 2
"""History's default: a whole state every 2 ticks (`World`'s ``keyframe_every``)."""


class World:
    """A simulated world the brain owns; one tick is described in `world.stepper`.

    ``compiled`` picks how a tick runs the schedule: True, the structure's tick as one generated
    function (`Structure.compiled`, the fast way); False, a plain loop over the same entries (to debug
    with). Both give bit-identical states. None: ``DYNABRAIN_COMPILED=0`` in the environment runs it
    plain, else generated. ``keyframe_every``: history keeps a whole state every that many ticks and
    after each edit or event, stepping the ticks between again when `backtick` goes to one (bit for
    bit); 1 keeps a state every tick (`History`; the trade is measured by ``bench/kernel.py``).
    ``module_factory`` makes a module from its spec when `import_state` brings one this world lacks;
    ``rebuild`` is a picklable call that builds this world again as it was at t=0 (a batch's worker
    processes use it). `load_world` gives both. A fork keeps all of these.

    ``core`` is a `PhysicsCore`, or an engine's name (``"mujoco"``, ``"exudyn"``) for a core named
    ``core`` on a 4 m square floor: the paper's Fig. 8 is ``w = World(core="mujoco")``, two
    `add_body` calls, ``w.make(["aa", "bb"])`` and ``w.tick("5s")``.
    """

    def __init__(self, name: str = "world", *, step: int | str = "2ms", seed: int = 0,
                 history: int = 1000, core: PhysicsCore | str | None = None, compiled: bool | None = None,
                 keyframe_every: int = KEYFRAME_EVERY,
                 module_factory: Callable[[dict[str, Any]], Module] | None = None,
                 rebuild: Callable[[], World] | None = None):
        self.name = name
        self.dt_ns = step if isinstance(step, int) else parse_duration_ns(step)
        if self.dt_ns <= 0:
            raise DynabrainError(f"the base step must be positive, got {step!r}")
        self.seed = int(seed)
        try:
            kept = History(history, every=keyframe_every)
        except ValueError as exc:
            raise DynabrainError(str(exc)) from None
        compiled = compiled_by_default() if compiled is None else bool(compiled)
        ctx = self._ctx = Context(name, self.dt_ns, self.seed, kept, compiled, module_factory, rebuild)
        ctx.world, ctx.view = self, WorldView(self)
        self._p = Parts.of(ctx)
        if isinstance(core, str):  # an engine's name: a core named "core" on a floor
            floor = BodySpec("floor", "plane", (FLOOR_HALF_M, FLOOR_HALF_M), color="grey")
            core = resolve_core(core)("core", SceneSpec(bodies=(floor,)))
        if core is not None:
            self.add_module(core)

    # -- read-only views ------------------------------------------------------------------------------
    tick_count = property(lambda self: self._ctx.tick, doc="The current tick.")
    time_ns = property(lambda self: self._ctx.tick * self.dt_ns, doc="Simulated time in ns.")
    core = property(lambda self: self._ctx.core, doc="The physics core, or None.")
    history = property(lambda self: self._ctx.history, doc="The states kept for rollback (`History`).")
    error = property(lambda self: self._ctx.error, doc="The error of the last failed tick, or None.")
    module_factory = property(lambda self: self._ctx.module_factory, doc="See the class docstring.")
    rebuild = property(lambda self: self._ctx.rebuild, doc="See the class docstring.")
    structure = property(lambda self: self._ctx.structure, doc="The current `Structure`: schedule, layout, loops.")
    bus = property(lambda self: self._ctx.ro, doc="The bus, read-only (laid out by ``structure.layout``).")
    compiled = property(lambda self: self._ctx.compiled, doc="Whether ticks run as generated code.")
    observers = property(lambda self: tuple(self._ctx.observers), doc="The observers, in the order told.")
    parts = property(lambda self: self._p, doc="The parts this face delegates to (benches and kernel tools).")
    connections = property(lambda self: self._ctx.structure.connections, doc="The connections.")
    running = property(lambda self: self._p.realtime.running, doc="Whether `start`'s thread runs.")

    @property
    def time(self) -> float:
        """Simulated time in seconds (``tick * step``, computed from integers)."""
        return self._ctx.tick * self.dt_ns / NS_PER_S

    @property
    def modules(self) -> dict[str, Module]:
        return {rec.name: rec.module for rec in self._ctx.structure.records}

    @property
    def signals(self) -> list[str]:
        """Every signal on the bus (``module.port``)."""
        return list(self._ctx.structure.layout.slots)

    @property
    def lock(self) -> Lock:
        """``with world.lock: ...`` (or ``world.lock()``, the lock itself) keeps the loop from stepping."""
        return Lock(self._ctx.lock)

    def schedule_order(self) -> list[str]:
        """Module names in the order they step within a tick."""
        return [step.record.name for step in self._ctx.structure.plan]

    # -- stepping and the timeline --------------------------------------------------------------------
    def tick(self, n: int | float | str = 1) -> None:
        """Advance ``n`` base steps (d-tick), or a duration: ``"1s"``, ``"250ms"``, or seconds as a float,
        a whole number of steps."""
        count = self.ticks_of(n, "tick")
        with self._ctx.lock:  # (not ``open``: a brain may tick one at a time; the C lock is cheaper)
            self._ctx.check_open()
            self._p.stepper.steps(count)

    def ticks_of(self, n: int | float | str, call: str = "ticks_of") -> int:
        """A tick count from a count (an int of 0 or more) or a duration (``"1s"``, or seconds as a
        float) that is a whole number of the world's steps; anything else is refused naming ``call``."""
        return self._p.stepper.ticks_of(n, call)

    def backtick(self, n: int = 1) -> None:
        """Go back ``n`` ticks, exactly (d-backtick): stepping forward again with the same inputs
        reproduces every state bit for bit."""
        with self._ctx.open:
            if n != 0:
                self._p.timeline.backtick(n)

    def snapshot(self) -> WorldState:
        """The whole world's state now; `restore` brings it back. Each snapshot has an ``id``, and
        observers get a ``snapshot`` event with it (a replay can then restore the same one)."""
        with self._ctx.open:
            return self._p.timeline.snapshot()

    def restore(self, state: WorldState) -> None:
        """Return to a snapshot of this world. History restarts at the restored state."""
        with self._ctx.open:
            if not isinstance(state, WorldState) or state.world_id != self._ctx.id:
                raise RollbackError("restore() takes a snapshot made by this same world (use fork() to copy)")
            self._p.timeline.check_restorable(state, "restore")
            self._p.timeline.restore(state, snapshot=state.id)

    def fork(self, name: str | None = None) -> World:
        """An independent world in the same state (for prediction: plan, try, discard), sharing what
        never changes (`Timeline.fork_into`). Close forks you are done with: a MuJoCo core's next fork
        takes over the closed one's data. The humanoid's fork costs are in ``bench/predict.py``."""
        with self._ctx.open:
            other = World(name or f"{self.name}-fork", step=self.dt_ns, seed=self.seed,
                          history=self._ctx.history.depth, compiled=self._ctx.compiled,
                          keyframe_every=self._ctx.history.every)
            self._p.timeline.fork_into(other._ctx)
            return other

    # -- structure edits ------------------------------------------------------------------------------
    def add_module(self, module: Module, *, period: int | str | None = None,
                   connect: Iterable[Connection | Sequence[Any]] = ()) -> None:
        """Add a module at the current tick (also while running): set up, bound and started now; on
        any failure the world is left as it was."""
        with self._ctx.open:
            self._p.wiring.add_module(module, period, connect)

    def remove_module(self, name: str) -> None:
        """Remove a module at the current tick. Inputs it drove keep their last value. The module
        stays alive (a rollback may bring it back) until the world closes."""
        with self._ctx.open:
            self._p.wiring.remove_module(name)

    def connect(self, src: str, dst: str, *, delay: bool = False) -> None:
        """Connect output ``src`` to input ``dst`` (both ``module.port``)."""
        with self._ctx.open:
            self._p.wiring.connect(src, dst, bool(delay))

    def disconnect(self, dst: str) -> None:
        """Remove the connection driving input ``dst`` (it keeps its last value)."""
        with self._ctx.open:
            self._p.wiring.disconnect(dst)

    def iterate(self, modules: Sequence[str], *, name: str | None = None, tolerance: float = 1e-9,
                max_iterations: int = 50) -> LoopSpec:
        """Declare ``modules`` (feedthrough, able to roll back, stepping at the same ticks) a loop iterated
        to agreement (strong coupling): each macro step is stepped again from their saved states until
        the torn values agree within ``tolerance`` (relative, plus as much absolute), at most
        ``max_iterations`` times, else the tick fails with `LoopNotConvergedError` and is rolled back.
        ``modules`` step in the order given; declare the loop before connecting it (`kernel.iterate`)."""
        with self._ctx.open:
            spec = LoopSpec(name or "loop_" + "_".join(modules), tuple(modules), float(tolerance), max_iterations)
            self._p.wiring.iterate(spec)
            return spec

    def loops(self) -> tuple[str, ...]:
        """The names of the loops iterated to agreement (`iterate`)."""
        return tuple(spec.name for spec in self._ctx.structure.loops)

    def loop_report(self, name: str) -> LoopReport | None:
        """How the last macro step of loop ``name`` went (iterations, residual, converged), or None."""
        return self._p.wiring.loop_report(name)

    # -- scene edits (the core's; part of history) -----------------------------------------------------
    def make(self, objects: Iterable[str], others: str = "frozen") -> None:
        """Simulate only ``objects`` (d-make; glob patterns such as ``box_*``). Every other object is
        ``"frozen"`` (a static obstacle where it stands) or ``"absent"`` (out of the simulation: the step
        costs what a scene of only ``objects`` costs). A later `make` that selects it brings it back
        there, at rest (`PhysicsCore.make`); a backtick across it undoes it."""
        with self._ctx.lock:
            self._p.scene.make(objects, others)

    def make_joint(self, a: str, b: str, name: str | None = None, *, kind: str = "weld",
                   axis: Sequence[Any] | None = None, anchor: Sequence[Any] | None = None) -> str:
        """Join bodies ``a`` and ``b`` as they stand (d-make-joint); returns the joint's name. ``kind``:
        ``weld`` (the default), ``hinge`` (about ``axis`` through ``anchor``), ``slider`` (along ``axis``)
        or ``ball`` (about ``anchor``), in the world frame (default z, and b's origin)."""
        with self._ctx.lock:
            return self._p.scene.make_joint(a, b, name, kind, axis, anchor)

    def remove_joint(self, name: str) -> None:
        """Remove a joint made at run time (`make_joint`)."""
        with self._ctx.lock:
            self._p.scene.remove_joint(name)

    def add_body(self, spec: BodySpec | None = None, /, **fields: Any) -> str:
        """Add a body while the world runs; returns its name. ``spec`` is a `BodySpec`, or its fields by
        name with a scenario's units and colours: ``world.add_body(name="box1", shape="box",
        size=["100mm"] * 3, mass="50g", pos=[0, 0, "1m"], color="blue", friction=0.4)``; a ``mesh`` body
        (an ``.obj`` or ``.stl`` file, or ``{vertices, faces}``) is simulated as its convex hull. It
        appears at rest, with ports of its own (``core.<name>.pos`` ...); a backtick before it takes it
        out again, bit for bit."""
        with self._ctx.lock:
            return self._p.scene.add_body(spec, fields)

    def remove_body(self, name: str) -> None:
        """Remove an object (a top-level body, with what hangs on it), its run-time joints, collision
        filters and connections to its ports; a backtick across it brings it back."""
        with self._ctx.lock:
            self._p.scene.remove_body(name)

    def set_material(self, body: str, *, friction: Any = KEEP, restitution: Any = KEEP, mass: Any = KEEP) -> None:
        """Give a body its own friction, restitution or mass from this tick on (None: the core's
        parameter again, the model's own mass); the same as ``world.set("core.<body>.friction", v)``.
        A mass scales the body's inertia with it (MuJoCo core only). Part of history and of forks."""
        with self._ctx.lock:
            self._p.scene.set_material(body, friction=friction, restitution=restitution, mass=mass)

    def material_target(self, name: str) -> tuple[str, str] | None:
        """(body, ``friction``, ``restitution`` or ``mass``) when ``name`` names a body's material."""
        return self._p.scene.material_target(name)

    def no_collision(self, objects: Iterable[str]) -> None:
        """Ignore contacts among ``objects`` (d-no-collision)."""
        with self._ctx.lock:
            self._p.scene.no_collision(objects)

    def place(self, body: str, pos: Sequence[float], quat: Sequence[float] | None = None) -> None:
        """Move a free body to a pose, at rest."""
        with self._ctx.lock:
            self._p.scene.place(body, pos, quat)

    # -- values by name -------------------------------------------------------------------------------
    def get(self, name: str) -> Any:
        """A signal (``module.port``; ``body.pos`` is short for the core's), a parameter (``module.param``),
        a body's material, or a body's field as expressions read it (``body.x``, ``.y``, ``.z``,
        ``.speed``, ``.vel``, ``.angvel``). Signals come back as copies."""
        with self._ctx.open:
            return self._p.names.get(name)

    def set(self, name: str, value: Any) -> None:
        """Set a run-time parameter (``module.param``), an unconnected input (``module.port``) or a body's
        material (``core.<body>.friction``, ``.restitution``, ``.mass``: `set_material`)."""
        with self._ctx.open:
            self._p.names.set(name, value)

    def settable(self, name: str) -> str | tuple[Module, str]:
        """What `set(name, ...)` would change: an input signal's full name, or (module, parameter).
        Raises, naming the closest settable name, when ``name`` cannot be set."""
        with self._ctx.lock:
            return self._p.names.settable(name)

    def signal_shape(self, name: str) -> tuple[int, ...]:
        """The shape of signal ``name``; an error naming the closest signal when there is none."""
        with self._ctx.lock:
            return self._p.names.signal_slot(name, "signal_shape()").shape

    # -- events and observers -------------------------------------------------------------------------
    def at(self, t: int | float | str, label: str, action: ScheduledAction) -> int:
        """Schedule ``action(world)`` at the start of the tick at time ``t`` (ns int, seconds float or a
        duration string); part of the world's definition: it fires again when a rollback replays its
        tick. Returns the tick."""
        return self._p.stepper.at(t, label, action)

    def scheduled_ticks(self) -> list[int]:
        """The ticks at which scheduled actions (a scenario's events) fire, in order."""
        with self._ctx.lock:
            return sorted(self._ctx.scheduled)

    def observe(self, observer: Observer) -> None:
        with self._ctx.lock:
            self._ctx.observers.append(observer)

    def unobserve(self, observer: Observer) -> None:
        with self._ctx.lock:
            self._ctx.observers.remove(observer)

    def imagine(self, name: str, start_tick: int, signals: Mapping[str, Any], branch: int = 0) -> Imagined:
        """Keep a future the brain imagined: every observer is told (an MCAP log writes it to
        ``/imagined/<name>/<branch>/...``). ``signals`` maps a signal to its values after each tick from
        ``start_tick`` on, shape ``(ticks, *shape)``; a signal of this world must have its shape, any
        other name is kept as given. The world does not change; a rollback does not discard it."""
        with self._ctx.open:
            return self._p.drive.imagine(name, start_tick, signals, branch)

    # -- driven runs, the loop in a thread ------------------------------------------------------------
    def run(self, ticks: int, *, inputs: Mapping[str, Any] | None = None,
            record: Sequence[str] = ()) -> dict[str, np.ndarray]:
        """Tick ``ticks`` times: before tick k each input named in ``inputs`` takes ``inputs[name][k]``
        (arrays of shape ``(ticks, *port shape)``), after it each signal in ``record`` is copied into row
        k. Returns ``{signal: array (ticks, *shape)}``. Names and shapes are checked first; a failed tick
        is rolled back as by `tick`, and its `ModuleError` carries ``recorded`` and ``ticks_done``."""
        with self._ctx.open:
            if int(ticks) < 0:
                raise DynabrainError(f"run({ticks}): the number of ticks must be >= 0")
            return self._p.drive.run(int(ticks), inputs or {}, record)

    def start(self, realtime: bool | float = False, *, until: float | None = None) -> None:
        """Run the loop in a thread (d-start). ``realtime``: False as fast as possible, True at real
        time, a number for a speed factor. ``until``: stop by itself at this simulated time (s)."""
        with self._ctx.open:
            factor = 1.0 if realtime is True else (float(realtime) if realtime else None)
            self._p.realtime.start(factor, None if until is None else round(until * NS_PER_S / self.dt_ns))

    def stop(self) -> None:
        """Stop the loop thread; re-raises an error that stopped it."""
        self._p.realtime.stop()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the loop thread to end by itself (``until``); True when it has."""
        return self._p.realtime.wait(timeout)

    # -- portable state -------------------------------------------------------------------------------
    def export_state(self, snapshot: WorldState | None = None) -> bytes:
        """The whole state (now, or of ``snapshot``) as versioned bytes that `import_state` takes back,
        in this world or in another built the same way (layout: `kernel.portable`)."""
        with self._ctx.open:
            return self._p.transfer.export(snapshot)

    def import_state(self, data: bytes) -> None:
        """Take back a state from `export_state`. Modules it has and this world lacks are made with
        ``module_factory``; modules only this world has leave. Refused, the world unchanged, when the
        worlds do not match (step, a module's class or ports, the version). History restarts there."""
        with self._ctx.open:
            self._p.transfer.import_(data)

    def check_state(self, data: bytes) -> None:
        """Raise `StateFormatError`, saying why, when `import_state` would refuse ``data``."""
        with self._ctx.lock:
            self._p.transfer.decode(data)

    # -- summary and closing --------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """A plain summary of the world."""
        with self._ctx.lock:
            kept = self._ctx.history
            return {"name": self.name, "tick": self._ctx.tick, "time": self.time, "step_ns": self.dt_ns,
                    "running": self.running, "modules": self.schedule_order(),
                    "history": {"depth": kept.depth, "available": kept.available,
                                "memory_bytes": kept.memory_bytes()},
                    "selection": list(self._ctx.core.selection) if self._ctx.core is not None else []}

    def close(self) -> None:
        """Stop, tell observers, close every module this world set up (d-end)."""
        with contextlib.suppress(BaseException):
            self.stop()
        with self._ctx.lock:
            self._ctx.close()

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

