"""The World: time, modules, the bus, history, and the brain's API (after EusDyna's d-* calls).

Every public method takes the world lock, so any of them may be called from another thread while
`start()` runs the loop; `with world.lock():` groups several calls so the loop cannot step between
them.

One tick (n -> n+1), the failure policy of each phase in brackets:

1. if the world was edited since the state of tick n was saved, save it again (edits are inputs);
2. fire the scenario's events due at tick n  [an error rolls back to tick n and is raised];
3. copy delayed connections; step each due module in schedule order, copying its direct inputs
   first  [an exception rolls back to tick n and is raised as `ModuleError`]; check that the outputs
   are finite  [a NaN or an infinity rolls back to tick n: `NonFiniteOutputError`, see `finite`];
4. tick = n+1; save the state in history (with keyframes, ``keyframe_every``: at every k-th tick and
   after events, else the tick's number only); tell observers.

Step 3 is one generated call (`CompiledTick.bind`), and step 4's history entry another
(`compiled.state_saver`); a rollback to a tick history holds by number restores the keyframe before
it and steps the ticks between again (`_replay`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fnmatch
import itertools
import re
import threading
import time as _time
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from . import portable
from .bodies import BodySpecError
from .compiled import CompiledTick, PlainTick, compiled_by_default, state_saver
from .core import KEEP, MAKE_OTHERS, BodySpec, PhysicsCore
from .errors import DynabrainError, ForkError, ModuleError, RollbackError, WiringError, WorldClosedError
from .history import History, WorldState
from .iterate import LoopReport, LoopSpec, loops_without
from .module import Module, SetupContext
from .observers import Imagined, Observer, WorldEvent, WorldView
from .structure import (
    SAVE_NONE,
    SAVE_PARAMS,
    UNRESTORABLE,
    Connection,
    ModuleRecord,
    Slot,
    Structure,
    build_structure,
    rebind_structure,
    split_signal,
)
from .suggest import did_you_mean
from .units import NS_PER_S, format_duration, parse_duration_ns

ScheduledAction = Callable[["World"], None]
KEYFRAME_EVERY = 2
"""History's default: a whole state every 2 ticks (`World`'s ``keyframe_every``)."""
_IMAGINED_NAME = re.compile(r"[A-Za-z0-9_.-]{1,100}")


class World:
    """A simulated world the brain owns. See the module docstring for one tick.

    ``compiled`` picks how a tick runs the schedule: True, the structure's tick as one generated
    function (`Structure.compiled`, the fast way); False, a plain loop over the same entries
    (`Structure.plain`), the one to debug with. Both give bit-identical states. Left out (None), the
    environment decides: ``DYNABRAIN_COMPILED=0`` runs every such world plain, which debugs a whole
    program without editing it; unset or ``1``, generated. A fork keeps its world's choice.

    ``keyframe_every``: history keeps a whole state every that many ticks (`KEYFRAME_EVERY`, 2, by
    default) and after each edit or event, stepping the ticks between again when `backtick` goes to
    one (bit for bit: the steps are deterministic, as rollback requires); 1 keeps a state every tick.
    The trade, measured (``bench/humanoid.py`` at 2 ms, ``bench/kernel.py``): a state every tick costs
    the humanoid about 2 us a tick more than one every 4 ticks and 1 us more than one every 2 (the
    capture, and 1000 states' memory touched and freed); a backtick(1) steps up to k - 1 ticks again:
    on average half a tick with k = 2 (0.86 of a physics step on 200 boxes, against 0.38 with k = 1 and
    1.9 with k = 4). A world with a module that cannot roll back keeps a state every tick. See
    `History` and the README. A fork keeps it.
    """

    def __init__(self, name: str = "world", *, step: int | str = "2ms", seed: int = 0,
                 history: int = 1000, core: PhysicsCore | None = None, compiled: bool | None = None,
                 keyframe_every: int = KEYFRAME_EVERY):
        self.name = name
        self.dt_ns = step if isinstance(step, int) else parse_duration_ns(step)
        if self.dt_ns <= 0:
            raise DynabrainError(f"the base step must be positive, got {step!r}")
        self.seed = int(seed)
        self._compiled = compiled_by_default() if compiled is None else bool(compiled)
        self._lock = threading.RLock()
        try:
            self._history = History(history, every=keyframe_every)
        except ValueError as exc:
            raise DynabrainError(str(exc)) from None
        self._structure = build_structure((), ())
        # what `_capture` saves, made again after a change of structure or parameters or a restore:
        self._params: tuple[dict[str, Any], ...] = ()  # every module's parameter dict, shared by states
        self._save_states: Callable[[], tuple] = tuple  # every module's state, in one call
        self._record: Callable[[int], None] = _nothing  # history's entry of a tick, in one call (`state_saver`)
        self._saver_of: Structure | None = None  # ... for this structure; None once a parameter changed
        # (the modules' bindings tell `_param_changed`) or a state was restored (`_apply`)
        self._buf = np.zeros(0)
        self._mv = memoryview(self._buf)  # the bus again: the tick's copies are cheaper on it
        self._ro = _read_only(self._buf)  # and read-only, for observers
        self._run_tick: Callable[[int, int], None] = _nothing  # the structure's tick on this bus (`CompiledTick.bind`)
        self._tick = 0
        self._dirty = True
        self._closed = False
        self._core: PhysicsCore | None = None
        self._observers: list[Observer] = []
        self._view = WorldView(self)
        self._scheduled: dict[int, list[tuple[str, ScheduledAction]]] = {}
        self._known: dict[int, Module] = {}  # every module ever set up here, closed at close()
        self._thread: threading.Thread | None = None
        self._stop_flag = threading.Event()
        self._thread_error: BaseException | None = None
        self._source = "api"  # who is editing: "scenario" while scheduled actions run
        self._snapshots = itertools.count(1)
        self._id = id(self)
        self._export_heads: dict[tuple[int, int], tuple] = {}  # export_state's headers (`_export_header`)
        self._signatures: dict[int, tuple[ModuleRecord, str]] = {}  # `_signature_of`
        self.error: BaseException | None = None
        self.module_factory: Callable[[dict[str, Any]], Module] | None = None
        """Makes a module from its spec (the scenario's module syntax) when `import_state` brings one this
        world lacks; the scenario layer sets it (`make_module` with the scenario's folder)."""
        self.rebuild: Callable[[], World] | None = None
        """A picklable call that builds this world again, as it was at t=0 (the scenario layer sets it:
        `load_world` of the same file); a batch's worker processes build their copies with it."""
        if core is not None:
            self.add_module(core)

    # -- properties ---------------------------------------------------------------------------------
    @property
    def tick_count(self) -> int:
        return self._tick

    @property
    def time(self) -> float:
        """Simulated time in seconds (``tick * step``, computed from integers)."""
        return self._tick * self.dt_ns / NS_PER_S

    @property
    def time_ns(self) -> int:
        return self._tick * self.dt_ns

    @property
    def core(self) -> PhysicsCore | None:
        return self._core

    @property
    def modules(self) -> dict[str, Module]:
        return {rec.name: rec.module for rec in self._structure.records}

    @property
    def connections(self) -> tuple[Connection, ...]:
        return self._structure.connections

    @property
    def history(self) -> History:
        return self._history

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def lock(self) -> _Lock:
        """The world lock: ``with world.lock: ...`` (or ``world.lock()``, the lock itself) keeps the loop
        from stepping in between."""
        return _Lock(self._lock)

    def schedule_order(self) -> list[str]:
        """Module names in the order they step within a tick."""
        return [step.record.name for step in self._structure.plan]

    @property
    def signals(self) -> list[str]:
        """Every signal on the bus (``module.port``), like `modules` and `connections` a property."""
        return list(self._structure.layout.slots)

    # -- stepping -------------------------------------------------------------------------------------
    def tick(self, n: int | float | str = 1) -> None:
        """Advance ``n`` base steps (d-tick), or a duration: ``"1s"``, ``"250ms"``, or seconds as a float,
        a whole number of steps."""
        count = self.ticks_of(n, "tick")
        with self._lock:
            self._check_open()
            self._steps(count)

    def ticks_of(self, n: int | float | str, call: str = "ticks_of") -> int:
        """A tick count from a count (an int of 0 or more) or a duration (``"1s"``, or seconds as a
        float) that is a whole number of the world's steps; anything else is refused naming ``call``."""
        if isinstance(n, bool) or not isinstance(n, (int, float, str, np.integer, np.floating)):
            raise DynabrainError(f"{call}: expected a tick count or a duration ('1s', or seconds as a float), "
                                 f"got {n!r}")
        if isinstance(n, (int, np.integer)):
            if n < 0:
                raise DynabrainError(f"{call}: {n} ticks; a count is 0 or more (backtick goes back)")
            return int(n)
        try:
            ns = parse_duration_ns(n if isinstance(n, str) else float(n), allow_frequency=False)
        except (DynabrainError, ValueError, TypeError, OverflowError) as exc:
            raise DynabrainError(f"{call}: {n!r} is not a duration: {exc}") from None
        if ns < 0 or ns % self.dt_ns:
            raise DynabrainError(f"{call}: {n!r} is not a whole number of the world's {format_duration(self.dt_ns)} "
                                 "steps (and not negative)")
        return ns // self.dt_ns

    def backtick(self, n: int = 1) -> None:
        """Go back ``n`` ticks, exactly (d-backtick). Stepping forward again with the same inputs
        reproduces every state bit for bit."""
        with self._lock:
            self._check_open()
            if n == 0:
                return
            target, ahead, inputs = self._history.restore_point(n)  # (a keyframe, the ticks after it, their inputs)
            self._check_restorable(target, f"backtick({n})")
            from_tick = self._tick
            self._history.drop_newest(n)
            self._apply(target)
            self._replay(ahead, inputs)
            self._dirty = False
            for obs in self._observers:
                obs.on_rollback(self._view, from_tick)

    def _step_once(self) -> None:
        self._steps(1)

    def _steps(self, count: int) -> None:
        """``count`` ticks (see the module docstring), each read from the world's attributes again (an
        event or an observer may edit the world between two). The hot path: what is not needed at
        every tick is in `_fire_events` and `_make_saver`."""
        scheduled, dt_ns = self._scheduled, self.dt_ns
        for _ in range(count):
            if self._dirty:
                self._history.replace_top(self._capture())
                self._dirty = False
            n = self._tick
            keyframe = False
            if n in scheduled:  # (events may change the structure, and with it `_run_tick`)
                keyframe = self._fire_events(n, scheduled[n])
            try:
                self._run_tick(n, n * dt_ns)  # the steps and the finite-output check (`CompiledTick.bind`)
            except Exception as exc:  # roll back to the last good tick, then report
                where = self._runner().failed_module(exc.__traceback__) or "?"  # the traceback says which module
                raise self._rollback_failed_tick(n, where, exc) from exc
            except BaseException:  # KeyboardInterrupt and the like: roll back, re-raise as is
                self._back_to(0)
                self._dirty = False
                raise
            self._tick = n + 1
            if self._saver_of is not self._structure:
                self._make_saver(self._structure)
            if keyframe:  # a whole state after events: stepping again from a keyframe never runs them twice
                self._history.push(self._capture())
            else:
                self._record(n + 1)  # history's entry, as `_capture` makes it
            self._dirty = False
            if self._observers:
                for obs in self._observers:
                    obs.on_tick(self._view)

    def _fire_events(self, n: int, events: list[tuple[str, ScheduledAction]]) -> bool:
        """Run the scenario's actions due at tick ``n`` (True when there were some); one that fails rolls
        the tick back and raises."""
        if not events:
            return False
        current = "?"
        self._source = "scenario"
        try:
            for label, action in events:
                current = label
                action(self)
        except Exception as exc:
            self._source = "api"
            raise self._rollback_failed_tick(n, f"event {current}", exc) from exc
        except BaseException:
            self._source = "api"
            self._back_to(0)
            self._dirty = False
            raise
        self._source = "api"
        return True

    def _runner(self) -> CompiledTick | PlainTick:
        """The tick the world runs (`_run_tick` is it, bound to the bus)."""
        return self._structure.compiled if self._compiled else self._structure.plain

    def _back_to(self, n: int) -> None:
        """Make the world what it was ``n`` ticks ago (0: at the current tick, after a failed one), from
        history's keyframe and the ticks stepped again after it; history itself is left as it is."""
        state, ahead, inputs = self._history.restore_point(n)
        self._apply(state)
        self._replay(ahead, inputs)

    def _replay(self, ticks: int, inputs: Sequence[Sequence[tuple[int, bytes]] | None]) -> None:
        """Step ``ticks`` ticks again from the keyframe just applied, as they ran: no events (a keyframe
        follows every tick that had some), no history entries, no observers; ``inputs[k]``: the inputs
        written before the step after the k-th (`History.restore_point`), written again. Steps that do
        not repeat themselves (a module that is not deterministic) raise a `RollbackError`, the world
        left at the keyframe and history cut after it."""
        dt_ns, mv = self.dt_ns, self._mv.cast("B")
        for done in range(ticks):
            n = self._tick
            try:
                self._run_tick(n, n * dt_ns)
            except Exception as exc:
                keyframe = n - done
                self._history.drop_newest(ticks)  # the ticks after the keyframe
                self._apply(self._history.top)
                raise RollbackError(f"stepping again from the keyframe at tick {keyframe} to tick {keyframe + ticks} "
                                    f"failed at tick {n} ({exc}); the world is at tick {keyframe}") from exc
            self._tick = n + 1
            for start, data in inputs[done] or ():
                mv[8 * start:8 * start + len(data)] = data

    def _rollback_failed_tick(self, n: int, where: str, exc: Exception) -> ModuleError:
        self._back_to(0)
        self._dirty = False
        if isinstance(exc, ModuleError):
            err = exc if exc.tick is not None else exc.at_tick(n)
        elif where.startswith("event"):
            err = ModuleError(where, "apply", n, exc)
        else:
            err = ModuleError(where, "step", n, exc)
        self.error = err
        self._emit("error", message=str(err), module=err.module, failed_tick=n)
        for obs in self._observers:
            obs.on_rollback(self._view, n)
        return err

    # -- state ----------------------------------------------------------------------------------------
    def _capture(self) -> WorldState:
        structure = self._structure
        if self._saver_of is not structure:
            self._make_saver(structure)
        return WorldState(self._id, self._tick, structure, self._buf.copy(), self._save_states(), self._params)

    def _make_saver(self, structure: Structure) -> None:
        """What each state of history holds until the structure or a parameter changes, or a state is
        restored: the modules' parameter dicts (one shared tuple), the state of each module whose
        steps leave it alone (`Module.steps_change_state`: saved now, then shared), and a call to
        ``get_state`` for the others; and `_record`, which pushes such a state after a tick."""
        self._params = tuple([rec.module._param_values for rec in structure.records])
        entries: list[tuple[bool, Any]] = []
        for rec, how in zip(structure.records, structure.saves, strict=True):
            module = rec.module
            if how == SAVE_NONE:
                entries.append((False, UNRESTORABLE))
            elif how == SAVE_PARAMS:
                entries.append((False, None))
            elif module.steps_change_state():
                entries.append((True, module.get_state))
            else:
                entries.append((False, module.get_state()))
        # the bus goes into history as bytes (`History`): half the cost of an array's copy, to make and to drop;
        # a state every tick while a module cannot roll back (stepping it again would repeat what it did)
        every = 1 if SAVE_NONE in structure.saves else self._history.every
        self._save_states, self._record = state_saver(entries, self._history.appender(), self._mv.tobytes,
                                                      (self._id, structure, self._params), every)
        self._saver_of = structure

    def _param_changed(self, module: Module) -> None:
        """A module bound here changed a parameter (`PortBinding.param_changed`): the states saved from
        now on hold its new parameter dict (and the state of a module whose steps leave it alone is
        taken again: `on_param` may have changed it)."""
        self._saver_of = None

    def _apply(self, state: WorldState) -> None:
        if state.structure is not self._structure:
            self._install(state.structure, carry_values=False)
        np.copyto(self._buf, state.bus)
        for rec, saved, params in zip(state.structure.records, state.states, state.params, strict=True):
            if saved is not UNRESTORABLE:
                rec.module._restore_params(params)
                rec.module.set_state(saved)
        self._tick = state.tick
        self._saver_of = None  # the states kept as they were may have been restored to others

    def _check_restorable(self, state: WorldState, what: str) -> None:
        bad = state.unrestorable()
        if bad:
            raise RollbackError(f"{what} refused: module(s) {', '.join(bad)} cannot roll back "
                                "(capability can_rollback is false)")

    def snapshot(self) -> WorldState:
        """The whole world's state now; `restore` brings it back. Each snapshot has an ``id``, and
        observers get a ``snapshot`` event with it (a replay can then restore the same one)."""
        with self._lock:
            self._check_open()
            state = self._capture()
            state.id = next(self._snapshots)
            self._emit("snapshot", id=state.id)
            return state

    def restore(self, state: WorldState) -> None:
        """Return to a snapshot of this world. History restarts at the restored state."""
        with self._lock:
            self._check_open()
            if not isinstance(state, WorldState) or state.world_id != self._id:
                raise RollbackError("restore() takes a snapshot made by this same world (use fork() to copy)")
            self._check_restorable(state, "restore")
            from_tick = self._tick
            self._apply(state)
            self._history.clear()
            self._history.push(state)
            self._dirty = False
            self._emit("restore", from_tick=from_tick, snapshot=state.id)
            for obs in self._observers:
                obs.on_rollback(self._view, from_tick)

    def fork(self, name: str | None = None) -> World:
        """An independent world in the same state (for prediction: plan, try, discard). It copies the
        state (the bus, each module's copy) and shares what never changes: the structure's layout,
        checks and copies (`rebind_structure`), the modules' parameter dicts, and what the modules
        share themselves (a MuJoCo core's compiled model, until either world changes a parameter).
        The humanoid's fork takes about 0.6 ms (bench/predict.py); close forks you are done with: a
        MuJoCo core's next fork takes over the closed one's data."""
        import copy

        with self._lock:
            self._check_open()
            refused = [r.name for r in self._structure.records if not r.module.CAPABILITIES.can_fork]
            if refused:
                raise ForkError(f"fork refused: module(s) {', '.join(refused)} cannot fork")
            memo: dict[int, Any] = {}
            bindings = {}  # modules are copied unbound (their copies are bound to the new world's bus)
            for rec in self._structure.records:
                bindings[rec.name] = rec.module.bind_ports(None)
                # shared, not copied: a parameter dict is replaced on a change, never changed in place
                # (history's states share it the same way)
                memo[id(rec.module._param_values)] = rec.module._param_values
            clones: dict[str, Module] = {}
            try:
                for rec in self._structure.records:
                    clones[rec.name] = copy.deepcopy(rec.module, memo)
            except BaseException:
                for clone in clones.values():  # free what was copied (FMU instances, processes)
                    _close_quietly(clone)
                raise
            finally:
                for rec in self._structure.records:
                    rec.module.bind_ports(bindings[rec.name])
            other = World(name or f"{self.name}-fork", step=self.dt_ns, seed=self.seed,
                          history=self._history.depth, compiled=self._compiled, keyframe_every=self._history.every)
            other._history.budget = self._history.budget  # a budget the scenario raised
            other._install(rebind_structure(self._structure, clones), carry_values=False, bus=self._buf)
            other._tick = self._tick
            other._scheduled = {k: list(v) for k, v in self._scheduled.items()}
            other.module_factory, other.rebuild = self.module_factory, self.rebuild
            other._core = clones.get(self._core.name) if self._core is not None else None
            other._known = {id(m): m for m in clones.values()}
            return other

    # -- structure edits ------------------------------------------------------------------------------
    def add_module(self, module: Module, *, period: int | str | None = None,
                   connect: Iterable[Connection | Sequence[Any]] = ()) -> None:
        """Add a module at the current tick (also while running). It is set up, bound and started
        now; on any failure the world is left as it was."""
        with self._lock:
            self._check_open()
            if not isinstance(module, Module):
                raise DynabrainError(f"add_module takes a Module, got {type(module).__name__}")
            if self._structure.record(module.name) is not None:
                raise WiringError(f"module name {module.name!r} is used twice")
            period_ns = self._period_ns(module, period)
            if isinstance(module, PhysicsCore) and self._core is not None:
                raise WiringError(f"world already has a physics core ({self._core.name!r})")
            ctx = SetupContext(self.name, self.dt_ns, period_ns, self._tick, self._rng_for(module.name),
                               module if isinstance(module, PhysicsCore) else self._core)
            _call(module, "setup", self._tick, module.setup, ctx)
            try:
                record = ModuleRecord(module.name, module, period_ns // self.dt_ns,
                                      self._tick % (period_ns // self.dt_ns), period_ns,
                                      tuple(module.inputs()), tuple(module.outputs()))
                conns = [as_connection(c) for c in connect]
                new = build_structure((*self._structure.records, record), (*self._structure.connections, *conns),
                                      self._structure.loops)
            except BaseException:
                _close_quietly(module)
                raise
            old = self._structure
            self._install(new, carry_values=True)
            try:
                module.bind()
                _call(module, "start", self._tick, module.start, self._tick * self.dt_ns)
            except BaseException:
                self._install(old, carry_values=True)
                _close_quietly(module)
                raise
            self._known[id(module)] = module
            if isinstance(module, PhysicsCore):
                self._core = module
            self._dirty = True
            self._emit("module_added", module=module.name, spec=module_spec(module, period_ns, conns))

    def remove_module(self, name: str) -> None:
        """Remove a module at the current tick. Inputs it drove keep their last value. The module
        stays alive (a rollback may bring it back) until the world closes."""
        with self._lock:
            self._check_open()
            rec = self._require_module(name)
            if rec.module is self._core:
                raise WiringError(f"the physics core {name!r} cannot be removed")
            records = [r for r in self._structure.records if r.name != name]
            conns = [c for c in self._structure.connections
                     if split_signal(c.src)[0] != name and split_signal(c.dst)[0] != name]
            self._install(build_structure(records, conns, loops_without(self._structure.loops, name)),
                          carry_values=True)
            self._dirty = True
            self._emit("module_removed", module=name)

    def connect(self, src: str, dst: str, *, delay: bool = False) -> None:
        """Connect output ``src`` to input ``dst`` (both ``module.port``)."""
        with self._lock:
            self._check_open()
            conn = Connection(src, dst, delay)
            self._install(build_structure(self._structure.records, (*self._structure.connections, conn),
                                          self._structure.loops), carry_values=True)
            self._dirty = True
            self._emit("connect", src=src, dst=dst, delay=delay)

    def iterate(self, modules: Sequence[str], *, name: str | None = None, tolerance: float = 1e-9,
                max_iterations: int = 50) -> LoopSpec:
        """Declare ``modules`` (feedthrough, able to roll back, stepping at the same ticks) a loop whose
        direct connections among each other may form cycles (strong coupling, issue 28): each macro step
        is stepped again from their saved states until the torn values agree within ``tolerance``
        (relative, plus as much absolute), at most ``max_iterations`` times; else the tick fails with
        `LoopNotConvergedError` and is rolled back. ``modules`` step in the order given. Declare the loop
        before connecting it. See `orchestrator.kernel.iterate`."""
        with self._lock:
            self._check_open()
            spec = LoopSpec(name or "loop_" + "_".join(modules), tuple(modules), float(tolerance), max_iterations)
            self._install(build_structure(self._structure.records, self._structure.connections,
                                          (*self._structure.loops, spec)), carry_values=True)
            self._dirty = True
            self._emit("iterate_declared", loop=spec.name, modules=list(spec.modules), tolerance=spec.tolerance,
                       max_iterations=spec.max_iterations)
            return spec

    def loops(self) -> tuple[str, ...]:
        """The names of the loops iterated to agreement (`iterate`)."""
        return tuple(spec.name for spec in self._structure.loops)

    def loop_report(self, name: str) -> LoopReport | None:
        """How the last macro step of loop ``name`` went (iterations, residual, converged), or None."""
        for runner in self._structure.runners:
            if runner.spec.name == name:
                return runner.last
        raise WiringError(f"no loop {name!r}" + did_you_mean(name, [r.spec.name for r in self._structure.runners]))

    def disconnect(self, dst: str) -> None:
        """Remove the connection driving input ``dst`` (it keeps its last value)."""
        with self._lock:
            self._check_open()
            if self._structure.driver_of(dst) is None:
                raise WiringError(f"no connection drives {dst!r}")
            conns = [c for c in self._structure.connections if c.dst != dst]
            self._install(build_structure(self._structure.records, conns, self._structure.loops), carry_values=True)
            self._dirty = True
            self._emit("disconnect", dst=dst)

    def _install(self, structure: Structure, *, carry_values: bool, bus: np.ndarray | None = None) -> None:
        """Make ``structure`` current: allocate the bus, carry values by name, rebind modules (each
        gets a `PortBinding` of the new bus through `Module.bind_ports`, then `bind` is called).
        ``bus``: the values the new bus starts with (a fork's: its world's bus, laid out the same);
        without it, the ports' start values (new ports begin there) and what is carried."""
        old_layout, old_buf = self._structure.layout, self._buf
        buf = structure.layout.new_bus() if bus is None else bus.copy()
        if carry_values:
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
        self._buf, self._mv, self._ro = buf, memoryview(buf), _read_only(buf)
        self._structure = structure
        self._run_tick = (structure.compiled if self._compiled else structure.plain).bind(self._mv, buf)
        self._saver_of = None  # `_record` copies the old bus
        for rec in structure.records:
            rec.module.bind_ports(structure.layout.modules[rec.name].binding(buf, self._ro, self._param_changed))
            rec.module.bind()
        for runner in structure.runners:  # iterate (issue 28): a loop's runner steps its members on this bus
            runner.bind(buf, self._emit)

    # -- scene edits (delegated to the core; part of its state) ----------------------------------------
    def make(self, objects: Iterable[str], others: str = "frozen") -> None:
        """Simulate only ``objects`` (d-make). Names may be glob patterns (``box_*``). ``others``: what
        becomes of every other object: ``"frozen"`` (the default) keeps it where it stands as a static
        obstacle; ``"absent"`` takes it out of the simulation (no geometry, no contacts: the step costs
        what a scene of only ``objects`` costs; select a floor too, or nothing holds the objects up).
        Either way its outputs hold where it stood and a later `make` that selects it brings it back
        there, at rest (`PhysicsCore.make`). Part of history: a backtick across it undoes it. A bad mode
        or name raises naming the field, and the world is left as it was."""
        with self._lock:
            core = self._require_core("make")
            if others not in MAKE_OTHERS:
                raise DynabrainError(f"make(), field others: unknown mode {others!r}"
                                     + did_you_mean(str(others), MAKE_OTHERS) + f"; one of: {', '.join(MAKE_OTHERS)}")
            names = expand_names(_names(objects), core.objects(), "object", "make")
            if others == "frozen":
                core.make(names)  # (a core of another author may not take ``others``)
            else:
                core.make(names, others)
            self._edited("make", objects=names, others=others)

    def make_joint(self, a: str, b: str, name: str | None = None, *, kind: str = "weld",
                   axis: Sequence[Any] | None = None, anchor: Sequence[Any] | None = None) -> str:
        """Join bodies ``a`` and ``b`` as they stand (d-make-joint); returns the joint's name. ``kind``:
        ``weld`` (rigid, the default), ``hinge`` (about ``axis`` through ``anchor``), ``slider`` (along
        ``axis``) or ``ball`` (about ``anchor``); ``axis`` and ``anchor`` in the world frame (default z,
        and b's origin; lengths may carry units). Part of history: a backtick across it undoes it."""
        with self._lock:
            core = self._require_core("make_joint")
            expand_names([a, b], core.bodies(), "body", "make_joint")
            extra = {k: v for k, v in (("axis", axis), ("anchor", anchor)) if v is not None}
            joint = core.make_joint(a, b, name, kind=kind, **extra) if extra or kind != "weld" else \
                core.make_joint(a, b, name)
            detail = {"a": a, "b": b, "joint": joint}
            if kind != "weld" or extra:
                detail["kind"] = kind
                detail.update({k: _world_values(v, k) for k, v in extra.items()})
            self._edited("make_joint", **detail)
            return joint

    # -- bodies at run time (the core's ports change: the structure is installed again) -----------------
    def add_body(self, spec: BodySpec | None = None, /, **fields: Any) -> str:
        """Add a body to the running world (also from another thread while `start` runs); returns its
        name. ``spec`` is a `BodySpec`, or its fields are given by name: ``world.add_body(name="box1",
        shape="box", size=["100mm"] * 3, mass="50g", pos=[0, 0, "1m"], color="blue", friction=0.4)``,
        with the units and colour names of a scenario file; a ``mesh`` body takes ``mesh`` (an ``.obj`` or
        ``.stl`` file, read now, or ``{vertices, faces}``) and ``scale``, and is simulated as its convex
        hull (see `BodySpec`). It appears at rest where ``pos`` and
        ``quat`` put it, simulated (`make` and `no_collision` take it by name), with ports of its own
        (``core.<name>.pos`` ..., and the inputs of a free body). Part of history: a backtick to a tick
        before it takes it out again, bit for bit. A bad value, or a name in use, raises naming the
        field, and the world is left as it was."""
        with self._lock:
            core = self._require_core("add_body")
            try:
                spec = spec if isinstance(spec, BodySpec) and not fields else BodySpec(**fields)
            except BodySpecError as exc:
                raise BodySpecError(exc.body, exc.field, exc.detail, call="add_body") from None
            except TypeError as exc:
                raise DynabrainError(f"add_body(): {exc} (a BodySpec, or its fields by name: name, shape, size, "
                                     "pos, quat, mass, color, joint, friction, restitution, mesh, scale)") from None
            self._edit_bodies(core, lambda: core.add_body(spec))
            self._edited("body_added", body=spec.name, spec=_body_detail(spec))
            return spec.name

    def remove_body(self, name: str) -> None:
        """Remove an object (a top-level body, with what hangs on it) from the running world: a body
        added at run time, or one of the scene's primitives. Its run-time joints and collision filters
        go with it, and so do connections to its ports (the inputs they drove keep their last value).
        Part of history: a backtick across it brings it back."""
        with self._lock:
            core = self._require_core("remove_body")
            dropped = self._edit_bodies(core, lambda: core.remove_body(name))
            self._edited("body_removed", body=name, disconnected=[str(c) for c in dropped])

    def _edit_bodies(self, core: PhysicsCore, edit: Callable[[], None]) -> list[Connection]:
        """Make a core edit that changes the core's ports, then install a structure with its new ports
        (`_core_ports_changed`); when that fails the core goes back to its state before."""
        before = core.get_state()
        edit()
        try:
            return self._core_ports_changed()
        except BaseException:
            core.set_state(before)
            raise

    def _core_ports_changed(self) -> list[Connection]:
        """After a core edit that changed its ports (bodies added or removed), a structure with the
        core's new ports replaces the current one (values carried by name; connections to ports that
        are gone are dropped and returned). History keeps the old structure: a rollback installs it
        again, and the core takes the old ports back when it is bound to them."""
        core = self._core
        assert core is not None
        rec = self._require_module(core.name)
        ins, outs = tuple(core.inputs()), tuple(core.outputs())
        if ins == rec.inputs and outs == rec.outputs:
            return []
        names = {f"{core.name}.{p.name}" for p in (*ins, *outs)}
        prefix = f"{core.name}."
        gone = [c for c in self._structure.connections
                if any(end.startswith(prefix) and end not in names for end in (c.src, c.dst))]
        records = [dataclasses.replace(r, inputs=ins, outputs=outs) if r is rec else r for r in self._structure.records]
        structure = build_structure(records, [c for c in self._structure.connections if c not in gone],
                                    self._structure.loops)
        self._install(structure, carry_values=True)
        core.refresh_outputs()
        self._dirty = True
        return gone

    # -- per-body materials ------------------------------------------------------------------------------
    def set_material(self, body: str, *, friction: Any = KEEP, restitution: Any = KEEP, mass: Any = KEEP) -> None:
        """Give a body its own friction, restitution or mass (None: the core's parameter again, the
        model's own mass), from this tick on; the same as ``world.set("core.<body>.friction", value)``
        (``.restitution``, ``.mass``). Part of history (a backtick undoes it) and of forks; contacts of
        the body with one that has no coefficient of its own take the body's. A mass scales the body's
        inertia with it (MuJoCo core only)."""
        with self._lock:
            core = self._require_core("set_material")
            expand_names([body], core.bodies(), "body", "set_material")
            core.set_material(body, friction=friction, restitution=restitution, mass=mass)
            m = core.material(body)
            self._edited("material", body=body, friction=m.friction, restitution=m.restitution, mass=m.mass)

    def material_target(self, name: str) -> tuple[str, str] | None:
        """(body, ``friction``, ``restitution`` or ``mass``) when ``name`` is ``<core>.<body>.friction``,
        ``.restitution`` or ``.mass`` (or without the core's name) of a body of the core, else None."""
        core = self._core
        if core is None:
            return None
        rest = name[len(core.name) + 1:] if name.startswith(f"{core.name}.") else name
        body, _, key = rest.rpartition(".")
        if key in ("friction", "restitution", "mass") and body in core.bodies():
            return body, key
        return None

    def remove_joint(self, name: str) -> None:
        with self._lock:
            self._require_core("remove_joint").remove_joint(name)
            self._edited("remove_joint", joint=name)

    def no_collision(self, objects: Iterable[str]) -> None:
        """Ignore contacts among ``objects`` (d-no-collision)."""
        with self._lock:
            core = self._require_core("no_collision")
            names = expand_names(_names(objects), core.bodies(), "body", "no_collision")
            core.no_collision(names)
            self._edited("no_collision", objects=names)

    def place(self, body: str, pos: Sequence[float], quat: Sequence[float] | None = None) -> None:
        """Move a free body to a pose, at rest."""
        with self._lock:
            core = self._require_core("place")
            expand_names([body], core.bodies(), "body", "place")
            core.place(body, pos, quat)
            self._write_core_outputs()
            self._edited("place", body=body, pos=list(map(float, pos)),
                         quat=None if quat is None else list(map(float, quat)))

    def _write_core_outputs(self) -> None:
        if self._core is not None:
            self._core.refresh_outputs()

    def _edited(self, kind: str, /, **detail: Any) -> None:
        self._dirty = True
        self._emit(kind, **detail)

    # -- values ---------------------------------------------------------------------------------------
    def get(self, name: str) -> Any:
        """A signal (``module.port``; ``body.pos`` is short for the core's ``body.pos``), a parameter
        (``module.param``), or a body's field as expressions read it (``body.x``, ``.y``, ``.z``,
        ``.speed``, ``.vel``, ``.angvel``). Signals come back as copies."""
        with self._lock:
            self._check_open()
            slot = self._resolve_signal(name)
            if slot is not None:
                value = self._buf[slot.start:slot.start + slot.size]
                return float(value[0]) if slot.shape == () else value.reshape(slot.shape).copy()
            material = self.material_target(name) if self._resolve_param(name) is None else None
            if material is not None:
                return getattr(self._core.material(material[0]), material[1])  # type: ignore[union-attr]
            field = self._body_field(name) if self._resolve_param(name) is None else None
            if field is not None:
                return field
            module, key = self._split_param(name)
            return module.params[key]

    def _body_field(self, name: str) -> Any:
        """``<body>.x`` (``.y``, ``.z``, ``.speed``, ``.vel``, ``.angvel``; the core's name may lead) of a
        body of the core, or None when ``name`` is no such field."""
        core = self._core
        if core is None:
            return None
        rest = name[len(core.name) + 1:] if name.startswith(f"{core.name}.") else name
        body, _, key = rest.rpartition(".")
        if key not in BODY_FIELDS or body not in core.bodies():
            return None
        if key in ("x", "y", "z"):
            return float(core.body_pose(body)[0]["xyz".index(key)])
        linear, angular = core.body_velocity(body)
        return {"vel": linear, "angvel": angular, "speed": float(np.linalg.norm(linear))}[key]

    def _resolve_param(self, name: str) -> tuple[Module, str] | None:
        module_name, sep, key = name.partition(".")
        rec = self._structure.record(module_name) if sep else None
        return (rec.module, key) if rec is not None and key in rec.module.param_specs() else None

    def set(self, name: str, value: Any) -> None:
        """Set a run-time parameter (``module.param``), an unconnected input (``module.port``) or a body's
        own friction or restitution (``core.<body>.friction``, ``.restitution``: `set_material`; None
        gives the body the core's again)."""
        with self._lock:
            self._check_open()
            if self._resolve_signal(name) is None and self._resolve_param(name) is None:
                material = self.material_target(name)
                if material is not None:
                    self.set_material(material[0], **{material[1]: value})
                    return
            target = self.settable(name)
            if isinstance(target, str):
                slot = self._structure.layout.slots[target]
                arr = np.asarray(value, dtype=np.float64)
                if arr.shape != slot.shape:
                    raise WiringError(f"{target} has shape {slot.shape}, got a value of shape {arr.shape}")
                values = arr.reshape(-1)
                self._buf[slot.start:slot.start + slot.size] = values
                self._keep_inputs([(slot.start, values.tobytes())])
                self._emit("set", name=target, value=arr.tolist())
                return
            module, key = target
            module.set_param(key, value, running=self._tick > 0)  # its binding tells `_param_changed`
            new = module.params[key]
            self._edited("param", name=f"{module.name}.{key}", value=new.tolist() if hasattr(new, "tolist") else new)

    def settable(self, name: str) -> str | tuple[Module, str]:
        """What `set(name, ...)` would change: an input signal's full name, or (module, parameter).
        Raises, naming the closest settable name, when ``name`` cannot be set."""
        with self._lock:
            slot = self._resolve_signal(name)
            if slot is not None:
                full = self._full_signal_name(name)
                if slot.direction != "in":
                    raise WiringError(f"{full} is an output of its module; only inputs and parameters can be set")
                conn = self._structure.driver_of(full)
                if conn is not None:
                    raise WiringError(f"{full} is driven by {conn.src}; disconnect it before setting it")
                return full
            return self._split_param(name, settable=True)

    def _full_signal_name(self, name: str) -> str:
        slots = self._structure.layout.slots
        if name in slots or self._core is None:
            return name
        return f"{self._core.name}.{name}"

    def _resolve_signal(self, name: str):
        slots = self._structure.layout.slots
        return slots.get(name) or (slots.get(f"{self._core.name}.{name}") if self._core is not None else None)

    def _split_param(self, name: str, settable: bool = False) -> tuple[Module, str]:
        module_name, sep, key = name.partition(".")
        rec = self._structure.record(module_name) if sep else None
        if rec is None or key not in rec.module.param_specs():
            layout = self._structure.layout.slots
            signals = [n for n in layout if not settable or layout[n].direction == "in"]
            candidates = [f"{r.name}.{p}" for r in self._structure.records for p in r.module.param_specs()] + signals
            raise DynabrainError(f"no signal or parameter named {name!r}" + did_you_mean(name, candidates))
        return rec.module, key

    # -- scenario events ------------------------------------------------------------------------------
    def at(self, t: int | float | str, label: str, action: ScheduledAction) -> int:
        """Schedule ``action(world)`` at the start of the tick at time ``t`` (ns int, seconds float
        or a duration string). Scheduled actions are part of the world's definition: they fire again
        when a rollback replays their tick. Returns the tick."""
        ns = t if isinstance(t, int) else parse_duration_ns(t if isinstance(t, str) else f"{t}s")
        if ns % self.dt_ns:
            raise DynabrainError(f"event {label!r} at {format_duration(ns)} is not on a tick of "
                                 f"{format_duration(self.dt_ns)}")
        tick = ns // self.dt_ns
        with self._lock:
            self._scheduled.setdefault(tick, []).append((label, action))
        return tick

    def scheduled_ticks(self) -> list[int]:
        """The ticks at which scheduled actions (a scenario's events) fire, in order."""
        with self._lock:
            return sorted(self._scheduled)

    # -- observers ------------------------------------------------------------------------------------
    def observe(self, observer: Observer) -> None:
        with self._lock:
            self._observers.append(observer)

    def unobserve(self, observer: Observer) -> None:
        with self._lock:
            self._observers.remove(observer)

    def _emit(self, kind: str, /, **detail: Any) -> None:
        if not self._observers:
            return
        event = WorldEvent(self._tick, kind, detail, self._source)
        for obs in self._observers:
            obs.on_event(self._view, event)

    def imagine(self, name: str, start_tick: int, signals: Mapping[str, Any], branch: int = 0) -> Imagined:
        """Keep a future the brain imagined (a planned or predicted branch): tell every observer (an MCAP
        log writes it to ``/imagined/<name>/<branch>/...``). ``signals`` maps a signal to its values after
        each tick from ``start_tick`` on, shape ``(ticks, *signal shape)`` (``BatchResult.imagine`` and
        ``Plan.imagine`` pass theirs). A signal of this world (``aa.pos`` is short for the core's) is
        named in full and must have its shape; any other name is kept as given, with no unit. The world
        does not change, and a rollback does not discard what was imagined."""
        if not isinstance(name, str) or not _IMAGINED_NAME.fullmatch(name):
            raise DynabrainError(f"imagine: the name {name!r} must be letters, digits, '_', '-' or '.'")
        for what, value in (("start_tick", start_tick), ("branch", branch)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise DynabrainError(f"imagine({name!r}): {what} must be an integer >= 0, got {value!r}")
        if not isinstance(signals, Mapping) or not signals:
            raise DynabrainError(f"imagine({name!r}): signals is a mapping of signal -> values (ticks, *shape)")
        with self._lock:
            self._check_open()
            values: dict[str, np.ndarray] = {}
            units: dict[str, str] = {}
            ticks = None
            for given, rows in signals.items():
                try:
                    arr = np.array(rows, dtype=np.float64)  # a copy: the caller may change its array
                except (TypeError, ValueError) as exc:
                    raise DynabrainError(f"imagine({name!r}): the values of {given} are not numbers: {exc}") from None
                slot = self._resolve_signal(given) if isinstance(given, str) else None
                full = self._full_signal_name(given) if slot is not None else given
                if slot is not None and arr.shape[1:] != slot.shape:
                    raise WiringError(f"imagine({name!r}): the values of {full} have shape {arr.shape}; ticks of a "
                                      f"signal of shape {slot.shape} need (ticks, {', '.join(map(str, slot.shape))})")
                if arr.ndim == 0 or (ticks is not None and len(arr) != ticks) or len(arr) == 0:
                    raise DynabrainError(f"imagine({name!r}): every signal needs the same number (>= 1) of rows, "
                                         f"one per tick; {given} has shape {arr.shape}")
                ticks = len(arr)
                arr.flags.writeable = False
                values[str(full)] = arr
                units[str(full)] = slot.port.unit if slot is not None else ""
            imagined = Imagined(name, int(branch), int(start_tick), self.dt_ns, values, units, self._tick)
            for obs in self._observers:
                obs.on_imagined(self._view, imagined)
            return imagined

    # -- the loop in a thread -------------------------------------------------------------------------
    def start(self, realtime: bool | float = False, *, until: float | None = None) -> None:
        """Run the loop in a thread (d-start). ``realtime``: False as fast as possible, True at real
        time, a number for a speed factor. ``until``: stop by itself at this simulated time (s)."""
        with self._lock:
            self._check_open()
            if self.running:
                raise DynabrainError("the world is already running")
            self._stop_flag.clear()
            self._thread_error = None
            factor = 1.0 if realtime is True else (float(realtime) if realtime else None)
            stop_tick = None if until is None else round(until * NS_PER_S / self.dt_ns)
            self._thread = threading.Thread(target=self._run, args=(factor, stop_tick),
                                            name=f"dynabrain-{self.name}", daemon=True)
            self._thread.start()

    def _run(self, factor: float | None, stop_tick: int | None) -> None:
        wall0 = _time.perf_counter()
        stepped = 0
        while not self._stop_flag.is_set():
            with self._lock:
                if stop_tick is not None and self._tick >= stop_tick:
                    break
                try:
                    self._step_once()
                except BaseException as exc:
                    self._thread_error = exc
                    break
            stepped += 1
            if factor:
                ahead = wall0 + stepped * self.dt_ns / NS_PER_S / factor - _time.perf_counter()
                if ahead > 0:
                    self._stop_flag.wait(ahead)
            elif stepped % 64 == 0:
                _time.sleep(0)  # let callers waiting for the lock in

    def stop(self) -> None:
        """Stop the loop thread; re-raises an error that stopped it."""
        thread = self._thread
        if thread is None:
            return
        self._stop_flag.set()
        if thread is not threading.current_thread():
            thread.join()
        self._thread = None
        if self._thread_error is not None:
            err, self._thread_error = self._thread_error, None
            raise err

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the loop thread to end by itself (``until``); True when it has."""
        thread = self._thread
        if thread is None:
            return True
        thread.join(timeout)
        return not thread.is_alive()

    # -- closing --------------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop, tell observers, close every module this world set up (d-end)."""
        with contextlib.suppress(BaseException):
            self.stop()
        with self._lock:
            if self._closed:
                return
            for obs in list(self._observers):
                with contextlib.suppress(Exception):
                    obs.on_close(self._view)
            self._closed = True
            for module in self._known.values():
                _close_quietly(module)
            self._known.clear()
            self._history.clear()

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- helpers --------------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise WorldClosedError(f"world {self.name!r} is closed")

    def _require_module(self, name: str) -> ModuleRecord:
        rec = self._structure.record(name)
        if rec is None:
            raise WiringError(f"no module {name!r}" + did_you_mean(name, self._structure.names))
        return rec

    def _require_core(self, call: str) -> PhysicsCore:
        self._check_open()
        if self._core is None:
            raise DynabrainError(f"{call}() needs a physics core, and this world has none")
        return self._core

    def _period_ns(self, module: Module, period: int | str | None) -> int:
        value = period if period is not None else module.DEFAULT_PERIOD
        ns = self.dt_ns if value is None else (value if isinstance(value, int) else parse_duration_ns(value))
        if ns <= 0 or ns % self.dt_ns:
            raise WiringError(f"module {module.name!r}: period {format_duration(ns)} is not a whole multiple "
                              f"of the base step {format_duration(self.dt_ns)}")
        return ns

    def _rng_for(self, name: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, zlib.crc32(name.encode())])

    # -- portable state and driven runs ------------------------------------------------------------------
    def export_state(self, snapshot: WorldState | None = None) -> bytes:
        """The whole state (now, or of ``snapshot``, a state of this world) as versioned bytes that
        `import_state` takes back, in this world or in another built the same way (another process,
        another host). The layout is documented in `kernel.portable`."""
        with self._lock:
            self._check_open()
            state = self._capture() if snapshot is None else snapshot
            if not isinstance(state, WorldState) or state.world_id != self._id:
                raise RollbackError("export_state() takes a snapshot made by this same world")
            self._check_restorable(state, "export_state")
            records = state.structure.records
            return portable.encode(self._export_header(state), state.bus, state.states, state.params,
                                   lambda i: records[i].name)

    def _export_header(self, state: WorldState) -> dict[str, Any]:
        """The header's fields but the tick: made once per structure and set of parameter dicts (the
        cache holds them, so their ids stay theirs)."""
        key = (id(state.structure), id(state.params))
        hit = self._export_heads.get(key)
        if hit is None or hit[0] is not state.structure or hit[1] is not state.params:
            modules = [{"name": r.name, "class": f"{type(r.module).__module__}:{type(r.module).__qualname__}",
                        "signature": self._signature_of(r),
                        "period_ns": r.period_ns, "phase": r.phase,
                        "spec": module_spec(r.module, r.period_ns)} for r in state.structure.records]
            conns = [[c.src, c.dst, c.delay] for c in state.structure.connections]
            head = {"world": self.name, "step_ns": self.dt_ns, "modules": modules, "connections": conns,
                    "bus": int(state.bus.size)}
            if len(self._export_heads) >= 8:
                self._export_heads.clear()
            hit = self._export_heads[key] = (state.structure, state.params, head)
        return {**hit[2], "tick": state.tick}

    def import_state(self, data: bytes) -> None:
        """Take back a state from `export_state` (of this world or of another built the same way).
        Modules the state has and this world lacks are made from their recorded spec with
        ``module_factory``; modules this world has and the state lacks leave the structure. Refused,
        with the world unchanged, when the worlds do not match (name, step, a module's class or ports,
        the dynabrain version). History restarts at the imported state."""
        with self._lock:
            self._check_open()
            ps = self._decode_state(data)
            structure = self._structure_for(ps)
            params = tuple(_same_params(rec.module._param_values, values)
                           for rec, values in zip(structure.records, ps.params, strict=True))
            state = WorldState(self._id, ps.tick, structure, ps.bus, ps.states, params)
            from_tick = self._tick
            self._apply(state)
            self._history.clear()
            self._history.push(state)
            self._dirty = False
            self._emit("restore", from_tick=from_tick, snapshot=0, imported=True)
            for obs in self._observers:
                obs.on_rollback(self._view, from_tick)

    def check_state(self, data: bytes) -> None:
        """Raise `StateFormatError`, saying why, when `import_state` would refuse ``data``: bytes that
        are not a state of this dynabrain, another base step, or a module of the same name that differs
        (class or ports: another scene). Modules only one side has do not count: import makes or drops them."""
        with self._lock:
            self._decode_state(data)

    def _decode_state(self, data: bytes) -> portable.PortableState:
        ps = portable.decode(data)
        if ps.step_ns != self.dt_ns:
            raise portable.StateFormatError(
                f"import_state: the state is of a world with step {format_duration(ps.step_ns)} (world "
                f"{ps.world!r}); this world's step is {format_duration(self.dt_ns)}")
        mine = {rec.name: rec for rec in self._structure.records}
        for entry, saved in zip(ps.modules, ps.states, strict=True):
            rec = mine.get(entry.name)
            if rec is None:
                continue
            cls = f"{type(rec.module).__module__}:{type(rec.module).__qualname__}"
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
        current = self._structure
        present = {r.name: r for r in current.records}
        other_ports = {}  # a core with other bodies in the state: its ports there (`_decode_state` checked them)
        for entry, saved in zip(ps.modules, ps.states, strict=True):
            rec = present.get(entry.name)
            if rec is not None and self._signature_of(rec) != entry.signature:
                other_ports[entry.name] = self._ports_in_state(rec.module, entry, saved)
        if not other_ports and (len(ps.modules) == len(current.records) and ps.connections == tuple(
                (c.src, c.dst, c.delay) for c in current.connections) and all(
                e.name == r.name and e.period_ns == r.period_ns and e.phase == r.phase
                for e, r in zip(ps.modules, current.records, strict=True))):
            return current  # the usual case (`_decode_state` has checked the modules)
        by_name: dict[str, ModuleRecord | Module] = {m.name: m for m in self._known.values()}  # removed ones too
        by_name.update({rec.name: rec for rec in current.records})
        made: list[Module] = []
        records: list[ModuleRecord] = []
        try:
            for entry in ps.modules:
                have = by_name.get(entry.name)
                if isinstance(have, ModuleRecord):  # present: checked by `_decode_state`
                    module, inputs, outputs = have.module, have.inputs, have.outputs
                    if other_ports.get(entry.name) is not None:  # a core with other bodies in the state
                        inputs, outputs = other_ports[entry.name]
                else:
                    module = have if have is not None else self._make_for_import(entry, made)
                    inputs, outputs = tuple(module.inputs()), tuple(module.outputs())
                    cls = f"{type(module).__module__}:{type(module).__qualname__}"
                    if cls != entry.cls or portable.signature(module, (*inputs, *outputs)) != entry.signature:
                        raise portable.StateFormatError(
                            f"import_state: module {entry.name!r} differs: the state's is {entry.cls}, this world's "
                            f"is {cls}" + (" with other ports (another scene or configuration?)"
                                           if cls == entry.cls else ""))
                records.append(ModuleRecord(entry.name, module, entry.period_ns // self.dt_ns, entry.phase,
                                            entry.period_ns, inputs, outputs))
            structure = build_structure(records, [Connection(s, d, x) for s, d, x in ps.connections],
                                        self._structure.loops)  # (loops: this world's, built the same way)
        except BaseException:
            for module in made:
                _close_quietly(module)
                self._known.pop(id(module), None)
            raise
        return structure

    def _make_for_import(self, entry: portable.ModuleEntry, made: list[Module]) -> Module:
        if self.module_factory is None:
            raise portable.StateFormatError(
                f"import_state: the state has module {entry.name!r} ({entry.cls}), which this world lacks, and the "
                "world has no module_factory to make it (a world from load_world has one)")
        module = self.module_factory(entry.spec)
        made.append(module)
        self._known[id(module)] = module
        ctx = SetupContext(self.name, self.dt_ns, entry.period_ns, self._tick, self._rng_for(module.name),
                           module if isinstance(module, PhysicsCore) else self._core)
        _call(module, "setup", self._tick, module.setup, ctx)
        return module

    def run(self, ticks: int, *, inputs: Mapping[str, Any] | None = None,
            record: Sequence[str] = ()) -> dict[str, np.ndarray]:
        """Tick ``ticks`` times, driving inputs and recording signals: before tick k each input port
        named in ``inputs`` takes ``inputs[name][k]`` (an array of shape ``(ticks, *port shape)``; the
        same as `set` before each `tick`), and after tick k each signal named in ``record`` is copied
        into row k of its array. Returns ``{signal: array (ticks, *shape)}``.

        Every name and shape is checked before the first tick. On a failure the world rolls back the
        failed tick as `tick` does, and the `ModuleError` raised carries ``recorded`` (the arrays, rows
        of the ticks not done NaN) and ``ticks_done``."""
        with self._lock:
            self._check_open()
            ticks = int(ticks)
            if ticks < 0:
                raise DynabrainError(f"run({ticks}): the number of ticks must be >= 0")
            drives = self._drives(inputs or {}, ticks)
            out = {name: np.full((ticks, *self._signal_slot(name, "run() record").shape), np.nan) for name in record}
            # rows cross as bytes (memoryview copies): each input's values as one bytes object, whose row k
            # is written into the bus and handed to history as it is (`History.written`)
            given = [(values.tobytes(), 8 * values.shape[1], values, name) for values, name in drives]
            rows = [(memoryview(out[name]).cast("B"), 8 * out[name][0].size, name) for name in out]
            structure, slots, bus = None, [], self._mv
            k = 0
            try:
                for k in range(ticks):
                    if self._structure is not structure:  # (an event may change it): find the slots again
                        structure, bus = self._structure, self._mv.cast("B")
                        slots = [(self._input_slot(name), raw, size, values, name) for raw, size, values, name in given]
                        recs = [(8 * self._signal_slot(name, "run() record").start, size, row)
                                for row, size, name in rows]
                    if slots:
                        spans = []
                        for slot, raw, size, values, name in slots:
                            row = raw[k * size:k * size + size]
                            bus[8 * slot.start:8 * slot.start + size] = row
                            spans.append((slot.start, row))
                            if self._observers:
                                self._emit("set", name=name, value=values[k].reshape(slot.shape).tolist())
                        self._keep_inputs(spans)
                    self._step_once()
                    for at, size, row in recs:
                        row[k * size:k * size + size] = bus[at:at + size]
            except ModuleError as err:
                err.recorded, err.ticks_done = out, k
                raise
            return out

    def _keep_inputs(self, spans: list[tuple[int, bytes]]) -> None:
        """Inputs just written into the bus at this tick (``(start, values as bytes)``), for history's
        state of this tick (`History.written`); when history cannot take them, the next tick saves a
        whole state."""
        if not self._dirty and not self._history.written(self._tick, spans, self._mv.tobytes):
            self._dirty = True

    def _drives(self, inputs: Mapping[str, Any], ticks: int) -> list[tuple[np.ndarray, str]]:
        drives = []
        for name, values in inputs.items():
            full = self.settable(name)
            if not isinstance(full, str):
                raise WiringError(f"run(): {name!r} is a parameter; inputs are input ports (set a parameter with set)")
            slot = self._structure.layout.slots[full]
            arr = np.asarray(values, dtype=np.float64)
            if arr.shape != (ticks, *slot.shape):
                raise WiringError(f"run(): the values for {full} have shape {arr.shape}; {ticks} ticks of a port of "
                                  f"shape {slot.shape} need {(ticks, *slot.shape)}")
            drives.append((arr.reshape(ticks, -1), full))
        return drives

    def signal_shape(self, name: str) -> tuple[int, ...]:
        """The shape of signal ``name`` (``module.port``, or a core port without ``core.``); an error
        naming the closest signal when there is none (a parameter's name is not a signal)."""
        with self._lock:
            return self._signal_slot(name, "signal_shape()").shape

    def _input_slot(self, full: str) -> Slot:
        self.settable(full)
        return self._structure.layout.slots[full]

    def _signal_slot(self, name: str, what: str) -> Slot:
        slot = self._resolve_signal(name)
        if slot is None:
            raise WiringError(f"{what}: no signal {name!r}" + did_you_mean(name, list(self._structure.layout.slots)))
        return slot

    def status(self) -> dict[str, Any]:
        """A plain summary of the world."""
        with self._lock:
            return {
                "name": self.name, "tick": self._tick, "time": self.time, "step_ns": self.dt_ns,
                "running": self.running, "modules": self.schedule_order(),
                "history": {"depth": self._history.depth, "available": self._history.available,
                            "memory_bytes": self._history.memory_bytes()},
                "selection": list(self._core.selection) if self._core is not None else [],
            }


def module_spec(module: Module, period_ns: int, connections: Sequence[Connection] = ()) -> dict[str, Any]:
    """A plain description from which the same module can be made again (logs, replay, the bridge):
    the scenario's module syntax, with parameters in SI."""
    spec = dict(module.scenario_spec())  # a class path by default; an FMU module says how it is made
    spec["period"] = f"{period_ns}ns"
    if module.targets:
        spec["targets"] = list(module.targets)
    if connections:
        spec["connect"] = [[c.src, c.dst, {"delay": True}] if c.delay else [c.src, c.dst] for c in connections]
    return spec


def _same_params(current: dict[str, Any], values: dict[str, Any]) -> dict[str, Any]:
    """``current`` itself when ``values`` holds the same parameters (an imported state's dicts are new
    objects: keeping the module's own spares it `on_param` calls for values that did not change)."""
    if current.keys() != values.keys():
        return values
    for key, value in values.items():
        mine = current[key]
        if mine is value:
            continue
        if isinstance(mine, np.ndarray) or isinstance(value, np.ndarray):
            if not (isinstance(mine, np.ndarray) and isinstance(value, np.ndarray) and mine.dtype == value.dtype
                    and np.array_equal(mine, value)):
                return values
        elif type(mine) is not type(value) or mine != value:
            return values
    return current


def _body_detail(spec: BodySpec) -> dict[str, Any]:
    """A body's spec as plain values in SI (an event's detail: logs, replay)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(spec):
        value = getattr(spec, f.name)
        if f.name == "line" or value is None:
            continue
        out[f.name] = dataclasses.asdict(value) if dataclasses.is_dataclass(value) else (
            value.plain() if f.name == "mesh" else list(value) if isinstance(value, tuple) else value)
    return out


def _world_values(value: Sequence[Any], key: str) -> list[float]:
    """A joint's axis or anchor as numbers in SI (an event's detail; the core has checked them)."""
    from .bodies import quantities

    return [float(x) for x in quantities(value, 3, "length" if key == "anchor" else None)]


BODY_FIELDS = ("x", "y", "z", "speed", "vel", "angvel")
"""A body's fields `World.get` reads besides its signals (as a scenario's expressions do)."""


class _Lock:
    """The world lock as `World.lock` hands it out: a context manager itself (``with world.lock:``) and
    callable for the lock (``with world.lock():``, ``world.lock().acquire()``)."""

    __slots__ = ("_rlock",)

    def __init__(self, rlock: Any):
        self._rlock = rlock

    def __call__(self) -> Any:
        return self._rlock

    def __enter__(self) -> Any:
        return self._rlock.__enter__()

    def __exit__(self, *exc: object) -> Any:
        return self._rlock.__exit__(*exc)


def _nothing(*_args: Any) -> None:
    """What a world with no modules yet runs for a tick, and records after it."""


def _read_only(buf: np.ndarray) -> np.ndarray:
    view = buf.view()
    view.setflags(write=False)
    return view


def as_connection(value: Connection | Sequence[Any]) -> Connection:
    if isinstance(value, Connection):
        return value
    if isinstance(value, str) or len(value) not in (2, 3):
        raise WiringError(f"a connection is [source, destination] or [source, destination, {{delay: true}}], "
                          f"got {value!r}")
    delay = bool(value[2].get("delay", False)) if len(value) == 3 and isinstance(value[2], dict) else False
    return Connection(str(value[0]), str(value[1]), delay)


def expand_names(names: Sequence[str], known: Sequence[str], kind: str, call: str) -> list[str]:
    """Names with glob patterns expanded against ``known``; an unknown name or empty pattern is an error."""
    out: list[str] = []
    for name in names:
        if any(ch in name for ch in "*?["):
            matched = fnmatch.filter(known, name)
            if not matched:
                raise DynabrainError(f"{call}(): pattern {name!r} matches no {kind}")
            out += [m for m in matched if m not in out]
        elif name not in known:
            raise DynabrainError(f"{call}(): unknown {kind} {name!r}" + did_you_mean(name, known))
        elif name not in out:
            out.append(name)
    return out


def _names(objects: Iterable[str] | str) -> list[str]:
    return [objects] if isinstance(objects, str) else [str(o) for o in objects]


def _call(module: Module, call: str, tick: int, fn: Callable[..., Any], *args: Any) -> Any:
    try:
        return fn(*args)
    except DynabrainError:
        raise
    except Exception as exc:
        raise ModuleError(module.name, call, tick, exc) from exc


def _close_quietly(module: Module) -> None:
    with contextlib.suppress(Exception):
        module.close()
