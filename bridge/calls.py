"""One World behind the bridge's calls, with no Zenoh in sight: views (named signals read as one binary
frame), snapshots by handle, brain inputs held until the next step boundary, batches of futures
(`batching`), and one method per call.

`WorldService.call(name, args)` runs a validated call and returns its result: plain JSON values, or
``bytes`` (a frame) for ``tick`` / ``read`` with a view and for ``batch``. A call either completes or
raises and changes nothing (the World's own guarantee; a failed tick is rolled back by the World). The calls it
answers are the world's calls of `protocol.TABLE`, one ``do_<call>`` method each; the server answers
the others (holds, forks, the loop, robots, its status).

Values from brains pass `checks` first (finite, within the scenario's limits; a parameter change that
makes the next tick fail is refused). A long ``tick`` runs in slices of about `SLICE_S` of wall-clock
time; between two slices the world lock is free and `WorldService.between_slices` (the server's hook)
answers other calls, and may end the tick (`StoppedTickError`).
"""

from __future__ import annotations

import fnmatch
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dynabrain.orchestrator.kernel.core import BodySpec
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.observers import WorldView
from dynabrain.orchestrator.kernel.specs import BodySpecError
from dynabrain.orchestrator.kernel.suggest import did_you_mean
from dynabrain.orchestrator.kernel.units import parse_duration_ns
from dynabrain.orchestrator.kernel.world import World, as_connection
from dynabrain.orchestrator.scenario.limits import MAX_MAGNITUDE, check_magnitudes
from dynabrain.orchestrator.scenario.make import ModuleNotAllowedError, make_module
from dynabrain.orchestrator.scenario.scene import parse_pose

from . import frames
from . import protocol as p
from .batching import BatchCall, BatchSettings, KeptState, Stored
from .checks import ValueRefusedError, check_pose, check_set, trial_set

DEFAULT_ALLOW_PYTHON: tuple[str, ...] = ()
"""Module classes a remote brain may add besides dynabrain's own, the registered ones (entry points of
``dynabrain.modules``) and the scenario folder's modules: package names (``mypkg``) or ``fnmatch``
patterns on ``package.module:Class``; a ``__main__`` module never (`kernel.plugins.ClassPolicy`)."""
STREAM_VIEW = 0
SLICE_S = 0.05
"""Wall-clock seconds a long ``tick`` runs before it lets other calls in (`WorldService.between_slices`)."""


class StoppedTickError(DynabrainError):
    """A ``stop`` ended a ``tick`` before its end: ``detail`` says how many ticks ran (they are kept)."""

    def __init__(self, message: str, detail: dict[str, Any]):
        super().__init__(message)
        self.detail = detail


@dataclass
class View:
    """Named signals, resolved against the bus layout of one structure."""

    id: int
    patterns: tuple[str, ...]
    names: tuple[str, ...] = ()
    shapes: tuple[tuple[int, ...], ...] = ()
    units: tuple[str, ...] = ()
    index: np.ndarray | None = None
    bus: object = None
    """The bus buffer the index was made for: a new buffer means a new structure."""

    def describe(self) -> dict[str, Any]:
        offsets, at = [], 0
        for shape in self.shapes:
            offsets.append(at)
            at += int(np.prod(shape, dtype=np.int64))
        return {"view": self.id, "size": at, "signals": [
            {"name": n, "shape": list(s), "unit": u, "offset": o}
            for n, s, u, o in zip(self.names, self.shapes, self.units, offsets, strict=True)]}


@dataclass(frozen=True)
class Rig:
    """A robot rig in the simulation: the servo module whose target input (``port``) motion commands set."""

    robot: str
    servo: str
    joints: tuple[str, ...]
    port: str = "target"

    @property
    def signal(self) -> str:
        return f"{self.servo}.{self.port}"


TARGET_PORTS = ("q_ref", "target")
"""Input ports of a servo that take the joints' target angles, in the order they are looked for: the
robot modules' `Servo` has ``q_ref``, the bridge's `PDServo` ``target``."""


def find_rig(world: World, robot: str, servo: str) -> Rig:
    """The rig of ``servo``: its target input and the joints in that input's order (from the input's
    per-joint view ports ``<joint>.<port>``)."""
    module = world.modules.get(servo)
    if module is None:
        raise DynabrainError(f"robot {robot!r}: no module {servo!r} in world {world.name!r}"
                             + did_you_mean(servo, world.modules))
    inputs = {port.name: port for port in module.inputs()}
    port = next((name for name in TARGET_PORTS if name in inputs and len(inputs[name].shape) == 1), None)
    if port is None:
        raise DynabrainError(f"robot {robot!r}: module {servo!r} has no target input "
                             f"({' or '.join(TARGET_PORTS)}, one value per joint)")
    joints: list[str | None] = [None] * inputs[port].shape[0]
    for p_ in inputs.values():
        if p_.view_of is not None and p_.view_of[0] == port and p_.name.endswith(f".{port}"):
            joints[p_.view_of[1]] = p_.name[:-len(port) - 1]
    if None in joints:
        raise DynabrainError(f"robot {robot!r}: cannot tell the joints of {servo}.{port} (no <joint>.{port} ports)")
    return Rig(robot, servo, tuple(joints), port)


class WorldService:
    """The calls of one World. Thread-safe through the World's own lock."""

    def __init__(self, world: World, *, instance: int, allow_python: Sequence[str] = DEFAULT_ALLOW_PYTHON,
                 base_dir: str | None = None, max_snapshots: int = 64, max_views: int = 256,
                 stream: Sequence[str] = (), batch: BatchSettings | None = None, trial_params: bool = True):
        self.world = world
        self.trial_params = trial_params
        """Try a run-time parameter change on a fork first, one tick (`checks.trial_set`)."""
        self.between_slices: Callable[[int, int], str | None] | None = None
        """Called between two slices of a long ``tick`` (the world lock free) with the ticks done and
        asked; returns None to go on, or who stopped the tick. None: a tick runs whole."""
        self.instance = instance
        self.allow_python = tuple(allow_python)
        self.base_dir = base_dir
        self.max_snapshots, self.max_views = max_snapshots, max_views
        self._wv = WorldView(world)
        self._views: dict[int, View] = {}
        self._next_view = 1
        self._snapshots: OrderedDict[int, Stored] = OrderedDict()
        self._next_snapshot = 0
        self._pending: dict[str, Any] = {}
        self._pending_lock = threading.Lock()
        self.applying_inputs = False
        self.input_errors: list[str] = []
        self.on_input_error: Callable[[str], None] | None = None
        self.rigs: dict[str, Rig] = {}
        self._handlers = p.handlers(self, server=False)
        # made now (its workers start at the first batch): a backend this world cannot use is refused at once
        self._batch = BatchCall(world, batch or BatchSettings("serial"), max_snapshots=max_snapshots)
        if stream:
            self._views[STREAM_VIEW] = self._resolve(View(STREAM_VIEW, tuple(stream)))

    # -- dispatch -------------------------------------------------------------------------------------------
    def call(self, name: str, args: Any) -> Any:
        handler = self._handlers.get(name)
        if handler is None:
            why = "the bridge server answers it" if name in p.TABLE else "no such call"
            raise DynabrainError(f"{name} is not a call of world {self.world.name!r} ({why})")
        return handler(args)

    # -- stepping -------------------------------------------------------------------------------------------
    def do_tick(self, a: p.TickArgs) -> Any:
        w, between = self.world, self.between_slices
        done = 0
        while True:
            with w.lock():
                if done == 0 and a.view is not None:
                    self.get_view(a.view)  # refused before any tick when the view is unknown
                end = time.monotonic() + SLICE_S if a.n > 1 else 0.0
                while done < a.n:
                    if self._pending:
                        self.apply_pending()
                    w.tick()
                    done += 1
                    if done < a.n and between is not None and time.monotonic() > end:
                        break
                if done >= a.n:
                    return self.frame(self.get_view(a.view)) if a.view is not None else None
            stopped_by = between(done, a.n)
            if stopped_by is not None:
                raise StoppedTickError(
                    f"tick stopped by brain {stopped_by!r} after {done} of {a.n} ticks (they are kept: the world "
                    f"is at tick {w.tick_count})",
                    {"ticks_done": done, "ticks_asked": a.n, "tick": w.tick_count, "by": stopped_by})

    def step_frame(self, a: p.TickArgs | p.ViewRef) -> bytes | None:
        """A one-step ``tick`` with a view, or a ``read``, in fewer steps than `do_tick` / `do_read`: the
        lock-step brain's hot path (the same tick, inputs and frame). None, before any tick, when the call
        is not that simple (several ticks, no view, a view unknown or made for another structure): the
        caller then runs the call's own handler, which resolves the view again or refuses it."""
        vid = a.view
        ticks = a.__class__ is p.TickArgs
        if vid is None or (ticks and a.n != 1):
            return None
        w = self.world
        with w.lock():
            view = self._views.get(vid)
            if view is None or self._wv.bus().base is not view.bus:
                return None
            if ticks:
                if self._pending:
                    self.apply_pending()
                w.tick()
                if self._wv.bus().base is not view.bus:  # the tick changed the structure (an event)
                    view = self.get_view(vid)
            return self.frame(view)

    def do_backtick(self, a: p.BacktickArgs) -> None:
        self.world.backtick(a.n)

    # -- scene edits ----------------------------------------------------------------------------------------
    def do_make(self, a: p.MakeArgs) -> Any:
        self.world.make(a.objects, others=a.others)
        return list(self.world.core.selection) if self.world.core is not None else []

    def do_make_joint(self, a: p.MakeJointArgs) -> str:
        return self.world.make_joint(a.a, a.b, a.name, kind=a.kind, axis=a.axis, anchor=a.anchor)

    # -- bodies at run time ---------------------------------------------------------------------------------
    def do_add_body(self, a: p.AddBodyArgs) -> dict[str, Any]:
        spec = make_body_spec(a.model_dump(exclude_none=True))
        with self.world.lock():
            before = set(self.world.signals)
            name = self.world.add_body(spec)
            return {"body": name, "signals": [s for s in self.world.signals if s not in before]}

    def do_remove_body(self, a: p.NameArgs) -> dict[str, Any]:
        with self.world.lock():
            n = len(self.world.connections)
            self.world.remove_body(a.name)
            return {"disconnected": n - len(self.world.connections)}

    def do_set_material(self, a: p.MaterialArgs) -> dict[str, Any]:
        given = {k: getattr(a, k) for k in ("friction", "restitution", "mass") if k in a.model_fields_set}
        with self.world.lock():
            self.world.set_material(a.body, **given)
            m = self.world.core.material(a.body)
            return {"friction": m.friction, "restitution": m.restitution, "mass": m.mass}

    def do_remove_joint(self, a: p.NameArgs) -> None:
        self.world.remove_joint(a.name)

    def do_no_collision(self, a: p.ObjectsArgs) -> None:
        self.world.no_collision(a.objects)

    def do_place(self, a: p.PlaceArgs) -> None:
        check_pose(a.body, a.pos, a.quat)
        self.world.place(a.body, a.pos, a.quat)

    # -- values ---------------------------------------------------------------------------------------------
    def do_set(self, a: p.SetArgs) -> None:
        self.set_checked(a.name, _value(a.value, a.name))

    def set_checked(self, name: str, value: Any) -> None:
        """`World.set` of a value from a brain, once `checks` let it: finite, within the limits, and (a
        run-time parameter, when ``trial_params``) not making the next tick fail."""
        with self.world.lock():
            target = check_set(self.world, name, value)
            if isinstance(target, tuple) and self.trial_params:
                trial_set(self.world, name, value)
            self.world.set(name, value)

    def do_get(self, a: p.NameArgs) -> Any:
        return p.plain(self.world.get(a.name))

    # -- modules and wiring ---------------------------------------------------------------------------------
    def do_add_module(self, a: p.AddModuleArgs) -> dict[str, Any]:
        spec = a.module
        module = self.make_module(spec)
        try:
            self.world.add_module(module, period=_period(spec.period),
                                  connect=[as_connection(c) for c in spec.connect])
        except BaseException:
            module.close()
            raise
        return {"module": spec.name, "order": self.world.schedule_order()}

    def make_module(self, spec: p.ModuleSpec) -> Any:
        """The module a client asks for: a ``python:`` class this server allows, or an FMU named
        relative to the scenario's folder."""
        if spec.fmu is not None:
            path = os.path.normpath(spec.fmu)
            if os.path.isabs(path) or path.startswith(".."):
                raise DynabrainError(f"module {spec.name!r}: an FMU is named relative to the scenario's folder, "
                                     f"got {spec.fmu!r}")
        try:
            check_magnitudes(spec.params, f"module {spec.name!r}: params")
        except DynabrainError as exc:
            raise ValueRefusedError(str(exc)) from None
        try:
            return make_module(spec, base_dir=self.base_dir or ".", allow_python=self.allow_python,
                               local_modules=self.base_dir is not None)  # (the scenario's folder, not the cwd)
        except ModuleNotAllowedError as exc:  # (refused before anything was imported)
            raise DynabrainError(f"add_module {spec.name!r}: {exc}; not allowed on this server (allowed besides "
                                 f"dynabrain's own and the registered: {', '.join(exc.allowed) or 'none'}; see "
                                 "`dynabrain serve --allow-python`)") from None

    def do_remove_module(self, a: p.NameArgs) -> list[str]:
        self.world.remove_module(a.name)
        return self.world.schedule_order()

    def do_connect(self, a: p.ConnectArgs) -> None:
        self.world.connect(a.src, a.dst, delay=a.delay)

    def do_disconnect(self, a: p.DisconnectArgs) -> None:
        self.world.disconnect(a.dst)

    # -- snapshots ------------------------------------------------------------------------------------------
    def do_snapshot(self, a: p.NoArgs) -> dict[str, Any]:
        state = self.world.snapshot()
        sid, evicted = self.keep(state)
        return {"snapshot": sid, "tick": state.tick, "evicted": evicted}

    def keep(self, state: Stored) -> tuple[int, list[int]]:
        """Keep a state under a new snapshot id; returns the id and those evicted to make room."""
        sid = self._next_snapshot
        self._next_snapshot += 1
        self._snapshots[sid] = state
        evicted = []
        while len(self._snapshots) > self.max_snapshots:
            evicted.append(self._snapshots.popitem(last=False)[0])
        return sid, evicted

    def do_restore(self, a: p.SnapshotRef) -> None:
        state = self._snapshot(a.snapshot)
        if isinstance(state, KeptState):  # a batch branch's final state
            self.world.import_state(state.data)
        else:
            self.world.restore(state)

    def do_drop_snapshot(self, a: p.SnapshotRef) -> None:
        self._snapshot(a.snapshot)
        del self._snapshots[a.snapshot]

    def _snapshot(self, sid: int) -> Stored:
        state = self._snapshots.get(sid)
        if state is None:
            raise DynabrainError(f"no snapshot {sid} on world {self.world.name!r} (dropped, evicted after "
                                 f"{self.max_snapshots}, or made before the server restarted)")
        return state

    # -- batches of futures ---------------------------------------------------------------------------------
    def do_batch(self, a: p.BatchArgs) -> bytes:
        """N futures of the world (`batching`): a BATCH frame; the world is only read."""
        return self._batch.run(a, snapshot=self._snapshot, keep=self.keep, instance=self.instance)

    def close(self) -> None:
        """Stop the batch's workers (the World itself stays open: its owner closes it)."""
        self._batch.close()

    # -- views ----------------------------------------------------------------------------------------------
    def do_view(self, a: p.ViewArgs) -> dict[str, Any]:
        if len(self._views) >= self.max_views:
            raise DynabrainError(f"too many views ({self.max_views}); drop some with drop_view")
        with self.world.lock():
            view = self._resolve(View(self._next_view, tuple(a.signals)))
        self._views[view.id] = view
        self._next_view += 1
        return view.describe()

    def do_read(self, a: p.ViewRef) -> bytes:
        with self.world.lock():
            return self.frame(self.get_view(a.view))

    def do_drop_view(self, a: p.ViewRef) -> None:
        if a.view == STREAM_VIEW:
            raise DynabrainError("view 0 is the state stream's; it cannot be dropped")
        if self._views.pop(a.view, None) is None:
            raise DynabrainError(f"no view {a.view}")

    def describe_view(self, vid: int) -> dict[str, Any]:
        with self.world.lock():
            return self.get_view(vid).describe()

    def get_view(self, vid: int) -> View:
        """A view, resolved again if the world's structure changed since (raises if a signal is gone)."""
        view = self._views.get(vid)
        if view is None:
            known = ", ".join(str(k) for k in self._views if k >= 0) or "none"
            raise DynabrainError(f"no view {vid} on world {self.world.name!r} (views: {known})")
        if self._wv.bus().base is not view.bus:
            self._resolve(view)  # the structure changed: find the signals again (raises if one is gone)
        return view

    def _resolve(self, view: View) -> View:
        slots = self._wv.signal_slots()
        names: list[str] = []
        for pattern in view.patterns:
            if any(ch in pattern for ch in "*?["):
                matched = [n for n in fnmatch.filter(slots, pattern) if n not in names]
                if not matched:
                    raise DynabrainError(f"view {view.id}: pattern {pattern!r} matches no signal")
                names += matched
            else:
                full = pattern if pattern in slots else self._core_name(pattern, slots)
                if full is None:
                    raise DynabrainError(f"view {view.id}: no signal {pattern!r}" + did_you_mean(pattern, slots))
                names.append(full)
        index = [np.arange(slots[n][0], slots[n][0] + int(np.prod(slots[n][1], dtype=np.int64))) for n in names]
        view.names = tuple(names)
        view.shapes = tuple(tuple(slots[n][1]) for n in names)
        view.units = tuple(slots[n][2] for n in names)
        view.index = np.concatenate(index).astype(np.intp) if index else np.zeros(0, dtype=np.intp)
        view.bus = self._wv.bus().base
        return view

    def _core_name(self, name: str, slots: dict) -> str | None:
        core = self.world.core
        full = f"{core.name}.{name}" if core is not None else None
        return full if full in slots else None

    def frame(self, view: View) -> bytes:
        """The view's values now, as a STATE frame (the caller holds the world lock)."""
        values = self._wv.bus().take(view.index)
        w = self.world
        return (frames.HEADER.pack(frames.MAGIC, frames.STATE, 0, self.instance, w.tick_count, w.time_ns, view.id,
                                   values.size) + values.astype("<f8", copy=False).tobytes())

    def has_view(self, vid: int) -> bool:
        return vid in self._views

    def internal_view(self, names: Sequence[str]) -> int:
        """A view for the bridge's own use (negative id, not listed to brains)."""
        vid = -1 - sum(1 for k in self._views if k < 0)
        with self.world.lock():
            self._views[vid] = self._resolve(View(vid, tuple(names)))
        return vid

    def values(self, vid: int) -> np.ndarray:
        """The values of a view now (the caller holds the world lock)."""
        return self._wv.bus().take(self.get_view(vid).index)

    @property
    def has_pending(self) -> bool:
        return bool(self._pending)

    # -- inputs at step boundaries --------------------------------------------------------------------------
    def submit(self, values: dict[str, Any]) -> None:
        """Hold values for inputs until the next step boundary (latest value per name wins)."""
        with self._pending_lock:
            self._pending.update(values)

    def apply_pending(self) -> None:
        """Set every held input value (the caller holds the world lock, between two ticks). A value that
        cannot be set is dropped and reported; the others are applied."""
        with self._pending_lock:
            pending, self._pending = self._pending, {}
        self.applying_inputs = True
        try:
            for name, value in pending.items():
                try:
                    self.set_checked(name, _value(value, name))
                except (DynabrainError, ValueError, TypeError) as exc:
                    self._input_error(f"input {name!r} dropped: {exc}")
        finally:
            self.applying_inputs = False

    def _input_error(self, message: str) -> None:
        self.input_errors = [*self.input_errors[-31:], message]
        if self.on_input_error is not None:
            self.on_input_error(message)

    # -- robot rigs -----------------------------------------------------------------------------------------
    def add_rig(self, robot: str, servo: str) -> Rig:
        rig = find_rig(self.world, robot, servo)
        self.rigs[robot] = rig
        return rig

    def rig(self, robot: str) -> Rig:
        rig = self.rigs.get(robot)
        if rig is None:
            raise DynabrainError(f"no robot {robot!r} on world {self.world.name!r}" + did_you_mean(robot, self.rigs)
                                 + (f"; robots: {', '.join(self.rigs)}" if self.rigs else
                                    "; serve with --robot NAME=SERVO to add one"))
        return rig

    def motion_inputs(self, rig: Rig, targets: list[float] | dict[str, float]) -> dict[str, Any]:
        """The input values a motion command sets on the rig's servo (checked now)."""
        if isinstance(targets, dict):
            for joint in targets:
                if joint not in rig.joints:
                    raise DynabrainError(f"robot {rig.robot!r} has no joint {joint!r}"
                                         + did_you_mean(joint, rig.joints))
            return {f"{rig.servo}.{j}.{rig.port}": _finite(v, j) for j, v in targets.items()}
        if len(targets) != len(rig.joints):
            raise DynabrainError(f"robot {rig.robot!r} has {len(rig.joints)} joints ({', '.join(rig.joints)}), "
                                 f"got {len(targets)} targets")
        return {rig.signal: [_finite(v, rig.joints[i]) for i, v in enumerate(targets)]}

    def status(self) -> dict[str, Any]:
        out = self.world.status()
        out["views"] = sum(1 for k in self._views if k >= 0)
        out["snapshots"] = list(self._snapshots)
        out["instance"] = self.instance
        out["batch"] = self._batch.describe()
        if STREAM_VIEW in self._views:
            out["stream"] = self.describe_view(STREAM_VIEW)
        out["robots"] = {r.robot: {"servo": r.servo, "input": r.signal, "joints": list(r.joints)}
                         for r in self.rigs.values()}
        return out


def _value(value: Any, name: str) -> Any:
    """A value to set: lists of numbers become arrays; structured lists (a servo's ``sequence`` of
    ``{pose, duration}`` steps, names) go to the module as they are."""
    return _numeric(value, name) if isinstance(value, list) and not _structured(value) else value


def _structured(value: Any) -> bool:
    if isinstance(value, (dict, str)):
        return True
    return isinstance(value, list) and any(_structured(v) for v in value)


def _numeric(value: list[Any], name: str) -> np.ndarray:
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DynabrainError(f"{name}: expected numbers (or lists of numbers), got {value!r:.80}") from None


def _finite(value: Any, joint: str) -> float:
    x = float(value)
    if not np.isfinite(x) or abs(x) > MAX_MAGNITUDE:
        raise ValueRefusedError(f"target of joint {joint!r} is not finite, or beyond ±{MAX_MAGNITUDE:g}: "
                                f"{value!r}")
    return x


def _period(value: Any) -> int | None:
    """A period as the scenario writes it (``10ms``, ``100Hz``, or seconds) in ns."""
    if value is None:
        return None
    if isinstance(value, bool):
        raise DynabrainError(f"period must be a duration (`10ms`) or seconds, got {value!r}")
    return parse_duration_ns(value)


def make_body_spec(fields: dict[str, Any]) -> BodySpec:
    """The `BodySpec` of an ``add_body`` call's fields (units and colour names checked: a bad value is
    refused naming the call, the body and the field)."""
    try:
        spec = BodySpec(**fields)
    except BodySpecError as exc:
        raise BodySpecError(exc.body, exc.field, exc.detail, call="add_body") from None
    try:  # a pose within the scenario's limits (as `place`)
        parse_pose({"pos": list(spec.pos), "quat": list(spec.quat)})
    except DynabrainError as exc:
        raise ValueRefusedError(f"add_body(): body {spec.name!r}, field pos/quat: {exc}") from None
    return spec
