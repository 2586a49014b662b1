"""``dynabrain replay LOG --verify``: rebuild the recorded world, re-simulate it, compare every tick.

The world is rebuilt from the scenario text in the log's metadata (written to a temporary folder, its
relative paths such as ``model:`` resolved against the original scenario's folder), with the recorded
seed and history depth. Then the recording is played back as a script: edits a brain made (events
whose source is ``api``: modules, parameters, inputs, selections, bodies added (from their recorded
spec, a mesh's vertices included) and removed, materials, joints of every kind) are applied at their
ticks, in their order; rollbacks are applied where they
happened (``backtick`` to the recorded tick; a ``restore`` to the snapshot the replay took at that tick
whose bus matches the recorded one; a failed tick must fail again). Every bus row the run produced,
discarded ones included, is compared bit for bit with the row the replay produces at the same epoch
and tick. The first difference is reported with its tick, signal and both values. What a brain
imagined (``/imagined/...``) is not compared: it is no part of the run. A log with no ticks at all
(nothing on ``/bus``) has nothing to verify and is refused (`LogError`; the CLI exits 2).

A log is not trusted further than a scenario: its module classes and FMUs are made under the same rules
(`kernel.plugins.ClassPolicy`, ``allow_python``), and a log written by another major or minor version
of dynabrain or MuJoCo is refused, saying which, unless ``allow_version_mismatch`` (the recorded versions
are stated either way: `VerifyResult.versions`). A recovered log whose middle chunks were lost has gaps
in its ticks: the replay steps through a gap without comparing (it re-simulates from the scenario, so
it needs no recorded state there), reports it (`VerifyResult.gaps`), and compares again from the first
tick recorded after it.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..kernel import edits
from ..kernel.errors import DynabrainError, ModuleError, ScenarioError
from ..kernel.observers import WorldView
from ..kernel.yamlsrc import MAX_FILE_BYTES
from ..scenario.make import ModuleSpecError, make_module
from ..scenario.model import load_scenario
from ..scenario.modelfile import ModelFileError, regular_file
from .meta import RunInfo, versions
from .read import BusRow, LogIndex, iter_bus, read_index
from .scan import LogError
from .schema import TOPIC_BUS, BusCodec

NEEDS = {**{kind: cls.needs() for kind, cls in edits.EDITS.items()},
         "rollback": ("from_tick", "to_tick", "cause"), "error": (), "snapshot": ("id",)}
"""What the detail of each replayed event kind must hold."""


@dataclass(frozen=True)
class Divergence:
    tick: int
    epoch: int
    message: str
    signal: str | None = None
    recorded: Any = None
    replayed: Any = None


@dataclass(frozen=True)
class VerifyResult:
    ok: bool
    rows: int
    """Bus rows compared (every tick the run produced, discarded ones included)."""
    ticks: int
    """Ticks re-simulated."""
    last_tick: int
    epochs: int
    wall_s: float
    divergence: Divergence | None = None
    versions: str = ""
    """The dynabrain and MuJoCo versions that wrote the log, and those that verified it."""
    gaps: tuple[tuple[int, int], ...] = ()
    """Ticks (first, last) the recording lacks (chunks lost and recovered around): stepped, not compared."""

    @property
    def ticks_per_s(self) -> float:
        return self.ticks / self.wall_s if self.wall_s > 0 else float("inf")


class _DivergedError(Exception):
    def __init__(self, divergence: Divergence):
        self.divergence = divergence


def verify(path: str | os.PathLike[str], *, allow_python: Sequence[str] = (),
           allow_version_mismatch: bool = False, progress: Callable[[int, int], None] | None = None) -> VerifyResult:
    """Re-simulate the run recorded in ``path`` and compare it tick by tick (see the module docstring).
    ``allow_python``: packages whose module classes the log may name (`Scenario.allow_python`).
    ``progress(rows compared, rows recorded)`` is called every few hundred rows, and at the end.
    Raises `LogError` / `ScenarioError` when there is nothing to verify against, or a version mismatch."""
    path = os.fspath(path)
    index = read_index(path)
    info = index.info
    if info is None:
        lib = index.header.library if index.header else ""
        if lib and not lib.startswith("dynabrain"):
            raise LogError(f"{path} is not a dynabrain recording (written by {lib!r}); it has no scenario to verify")
        raise LogError(f"{path} lacks the `dynabrain` metadata record (the run's scenario, seed and versions"
                       f"{'; its header says dynabrain wrote it' if lib else ''}): lost before the log was recovered, "
                       "or never written by a run killed early, so there is no scenario to verify against")
    if not info.scenario_text:
        raise LogError(f"{path} has no scenario: it records a world built in code, which --verify cannot rebuild")
    if info.start_tick != 0:
        raise LogError(f"{path} starts at tick {info.start_tick}: --verify needs a recording attached at tick 0")
    if not index.keys.get(TOPIC_BUS):
        raise LogError(f"{path} holds no ticks (no {TOPIC_BUS} messages), so there is nothing to verify (a run "
                       "killed before its first chunk was written recovers to such a log)")
    stated = check_versions(info, path, allow_version_mismatch)
    world = rebuild(info, path, allow_python)
    try:
        result = _Replay(world, index, path, info.scenario_dir or ".", progress).run()
    finally:
        world.close()
    return dataclasses.replace(result, versions=stated)


VERSIONED = ("dynabrain", "mujoco")
"""The packages whose major and minor versions must be the recording's (`check_versions`)."""


def check_versions(info: RunInfo, path: str, allow_mismatch: bool = False) -> str:
    """A line stating the `VERSIONED` packages' versions, recorded and here; a `LogError` saying which
    differs in its major or minor version, unless ``allow_mismatch``."""
    here = versions()
    parts, differ = [], []
    for name in VERSIONED:
        then, now = info.versions.get(name), here.get(name)
        parts.append(f"{name} {then or 'unrecorded'}" + (f" (here {now})" if now != then else ""))
        if then is not None and now is not None and _major_minor(then) != _major_minor(now):
            differ.append(f"{name} {then} wrote it, {now} is installed")
    stated = "recorded with " + ", ".join(parts)
    if differ and not allow_mismatch:
        raise LogError(f"{path}: {'; '.join(differ)}: another major or minor version may step differently, so a "
                       "difference would not tell a bug (pass --allow-version-mismatch to verify it all the same)")
    return stated + ("; verified despite the version mismatch" if differ else "")


def _major_minor(version: str) -> tuple[str, ...]:
    return tuple(version.split(".")[:2])


def rebuild(info: RunInfo, log_path: str, allow_python: Sequence[str] = ()) -> Any:
    """The recorded scenario, loaded again and built with the recorded seed and history depth."""
    original = info.scenario_path or os.path.join(info.scenario_dir or ".", "scenario.yaml")
    label = f"{original} (as recorded in {log_path})"
    with tempfile.TemporaryDirectory(prefix="dynabrain-verify-") as tmp:
        copy = os.path.join(tmp, os.path.basename(original) or "scenario.yaml")
        with open(copy, "w", encoding="utf-8") as fh:
            fh.write(info.scenario_text or "")
        try:
            sc = load_scenario(copy, allow_python)
        except ScenarioError as exc:
            raise ScenarioError([dataclasses.replace(p, file=label) for p in exc.problems]) from None
    sc.path = os.path.join(info.scenario_dir, os.path.basename(original)) if info.scenario_dir else original
    sc.local_modules = _still_there(original, info.scenario_text or "")
    sc.source.file = label
    if info.duration_ns is not None:
        sc.duration_ns = info.duration_ns
    return sc.build(seed=info.seed, history=info.history)


def _still_there(original: str, text: str) -> bool:
    """Whether the recorded scenario file is where the log says, holding what the log recorded: only then
    are the modules of its folder the scenario's own (a log may claim any folder)."""
    try:
        size = regular_file(original, "the recorded scenario", MAX_FILE_BYTES)
        with open(original, encoding="utf-8-sig", newline="") as fh:
            return size <= MAX_FILE_BYTES and fh.read(MAX_FILE_BYTES + 1) == text
    except (ModelFileError, OSError, UnicodeDecodeError):
        return False


class _Replay:
    def __init__(self, world: Any, index: LogIndex, path: str, base_dir: str,
                 progress: Callable[[int, int], None] | None = None):
        self.world, self.view, self.index, self.base_dir = world, WorldView(world), index, base_dir
        self._progress, self._rows_recorded = progress, len(index.keys.get(TOPIC_BUS, ()))
        self.gaps: list[tuple[int, int]] = []
        self._rows: Iterator = iter_bus(path, index, produced=True)
        self._peeked: BusRow | None = None
        self.epoch = self.compared = self.stepped = 0
        self._layout_ok: tuple[int, int] | None = None
        self.actions = [_checked(e, path) for e in index.events if e.get("kind") in ("rollback", "error")
                        or (e.get("source") == "api" and e.get("kind") in (*edits.EDITS, "snapshot"))]
        self.restore_ticks = {int(e["detail"]["to_tick"]) for e in self.actions
                              if e["kind"] == "rollback" and e["detail"].get("cause") == "restore"}
        self.snapshots: dict[int, list[Any]] = {}
        self.by_id: dict[int, Any] = {}  # the run's snapshot ids -> the replay's snapshots at the same point

    def run(self) -> VerifyResult:
        t0 = time.perf_counter()
        divergence = None
        try:
            if self._peek() is not None:
                self._compare(self._next())
            self._remember()
            for action in self.actions:
                rollback = action["kind"] == "rollback"  # recorded at the tick it went back to
                if not self._advance(int(action["detail"]["from_tick"] if rollback else action["tick"])):
                    break
                self._apply(action)
            while self._peek() is not None:
                self._step()
        except _DivergedError as exc:
            divergence = exc.divergence
        if self._progress is not None:
            self._progress(self.compared, self._rows_recorded)
        return VerifyResult(divergence is None, self.compared, self.stepped, self.world.tick_count, self.epoch,
                            time.perf_counter() - t0, divergence, gaps=tuple(self.gaps))

    # -- the recorded rows ----------------------------------------------------------------------------
    def _peek(self) -> BusRow | None:
        if self._peeked is None:
            self._peeked = next(self._rows, None)
        return self._peeked

    def _next(self) -> BusRow | None:
        row = self._peek()
        self._peeked = None
        return row

    def _fail(self, message: str, **kw: Any) -> None:
        raise _DivergedError(Divergence(self.world.tick_count, self.epoch, message, **kw))

    # -- stepping -------------------------------------------------------------------------------------
    def _advance(self, tick: int) -> bool:
        """Step up to ``tick``; False when the recording ends first (a recovered log)."""
        while self.world.tick_count < tick:
            if self._peek() is None:
                return False
            self._step()
        if self.world.tick_count != tick:
            self._fail(f"the recording has an event at tick {tick}, but the replay is already at tick "
                       f"{self.world.tick_count}")
        return True

    def _step(self) -> None:
        try:
            self.world.tick()
        except ModuleError as exc:
            self._fail(f"the replay failed where the run did not: {exc}")
        self.stepped += 1
        row, tick = self._peek(), self.world.tick_count
        if row is not None and row.epoch == self.epoch and row.tick > tick:  # the recording lacks this tick
            if self.gaps and self.gaps[-1][1] == tick - 1:
                self.gaps[-1] = (self.gaps[-1][0], tick)
            else:
                self.gaps.append((tick, tick))
        else:
            self._compare(self._next())
        self._remember()

    def _remember(self) -> None:
        if self.world.tick_count in self.restore_ticks:
            self.snapshots.setdefault(self.world.tick_count, []).append(self.world.snapshot())

    def _compare(self, row: BusRow | None) -> None:
        if row is None:
            self._fail("the replay produced a tick the recording does not have")
        codec, epoch, tick, recorded = row.codec, row.epoch, row.tick, row.row
        if (epoch, tick) != (self.epoch, self.world.tick_count):
            self._fail(f"the recording's next tick is {tick} (epoch {epoch}); the replay is at tick "
                       f"{self.world.tick_count} (epoch {self.epoch})")
        self._check_layout(codec)
        bus = self.view.bus()
        self.compared += 1
        if self._progress is not None and self.compared % 256 == 0:
            self._progress(self.compared, self._rows_recorded)
        if not np.array_equal(bus.view(np.int64), recorded.view(np.int64)):
            where = int(np.flatnonzero(bus.view(np.int64) != recorded.view(np.int64))[0])
            slot = min((s for s in codec.slots if s.offset <= where < s.offset + s.size), key=lambda s: s.size)
            part = slice(slot.offset, slot.offset + slot.size)
            self._fail(f"{slot.name} differs (first at component {where - slot.offset})", signal=slot.name,
                       recorded=_value(recorded[part], slot.shape), replayed=_value(bus[part], slot.shape))

    def _check_layout(self, codec: BusCodec) -> None:
        key = (codec.key, self.view.bus().size)
        if self._layout_ok == key:
            return
        now = {n: (o, tuple(sh), u) for n, (o, sh, u) in self.view.signal_slots().items()}
        then = {s.name: (s.offset, s.shape, s.unit) for s in codec.slots}
        if now != then:
            extra, missing = sorted(set(now) - set(then)), sorted(set(then) - set(now))
            self._fail(f"the bus layout differs: the replay has {len(now)} signals, the recording {len(then)}"
                       + (f"; only in the replay: {', '.join(extra[:5])}" if extra else "")
                       + (f"; only in the recording: {', '.join(missing[:5])}" if missing else ""))
        self._layout_ok = key

    # -- recorded actions -----------------------------------------------------------------------------
    def _apply(self, action: dict) -> None:
        kind, detail = action["kind"], action.get("detail", {})
        if kind == "error":
            self._fail_again(detail)
        elif kind == "snapshot":
            self.by_id[int(detail["id"])] = self.world.snapshot()
        elif kind == "rollback":
            self._rollback(detail)
        else:
            try:
                apply_edit(self.world, kind, detail, self.base_dir)
            except LogError:
                raise
            except DynabrainError as exc:
                self._fail(f"the recorded edit {kind} {detail} fails on replay: {exc}")
            self._layout_ok = None
            self._remember()

    def _fail_again(self, detail: dict) -> None:
        try:
            self.world.tick()
        except ModuleError as exc:
            if exc.module != detail.get("module"):
                self._fail(f"the replay failed in module {exc.module!r}, the run in {detail.get('module')!r}: {exc}")
            return
        self._fail(f"the run failed at this tick ({detail.get('message')}); the replay stepped without error")

    def _rollback(self, detail: dict) -> None:
        cause, to, frm = detail.get("cause"), int(detail["to_tick"]), int(detail["from_tick"])
        if cause != "failed_tick" and self.world.tick_count != frm:
            self._fail(f"the run rolled back from tick {frm}, the replay is at tick {self.world.tick_count}")
        if cause == "backtick":
            self.world.backtick(frm - to)
        self.epoch += 1
        self._layout_ok = None
        if cause == "restore":
            snap = self.by_id.get(int(detail.get("snapshot", 0)))
            self.world.restore(snap if snap is not None else self._snapshot_for(to))
            self._compare(self._next())
        self._remember()  # a snapshot taken right after this rollback may be restored later

    def _snapshot_for(self, tick: int) -> Any:
        candidates = self.snapshots.get(tick, [])
        if not candidates:
            self._fail(f"the run restored a snapshot of tick {tick}, which the replay never reached")
        row = self._peek()
        for snap in reversed(candidates):
            if row is not None and snap.bus.size == row.row.size and np.array_equal(snap.bus.view(np.int64),
                                                                                     row.row.view(np.int64)):
                return snap
        return candidates[-1]


def _checked(event: dict, path: str) -> dict:
    detail = event.get("detail")
    missing = [k for k in NEEDS[event["kind"]] if not isinstance(detail, dict) or k not in detail]
    if missing or not isinstance(event.get("tick"), int):
        raise LogError(f"{path}: event {event.get('seq')} ({event['kind']}) is damaged: it lacks "
                       + (", ".join(missing) if missing else "its tick"))
    return event


def apply_edit(world: Any, kind: str, d: dict, base_dir: str = ".") -> None:
    """Make a recorded edit again (an event of kind ``kind`` with detail ``d``: `kernel.edits`). A module
    is made by the world's ``module_factory`` (under the rules its scenario was loaded with: `rebuild`),
    else by `make_module` with no more than dynabrain's own and the registered classes; an FMU's path
    is relative to ``base_dir`` (the recorded scenario's folder)."""
    try:
        edit = edits.edit_of(kind, d)
    except edits.EditFormatError as exc:
        named = next((d[k] for k in ("body", "module", "joint", "name") if isinstance(d, dict) and k in d), None)
        raise LogError(f"the recording's {kind}" + (f" ({named!r})" if named is not None else "")
                       + f" at tick {world.tick_count} is damaged: {exc}") from None
    maker = world.module_factory or functools.partial(make_module, base_dir=base_dir, local_modules=False)
    try:
        edit.apply(world, maker)
    except ModuleSpecError as exc:  # nothing to compare with: the recording cannot be replayed here
        raise LogError(f"the recording adds module {d['spec'].get('name')!r} at tick {world.tick_count}, which "
                       f"cannot be made here: {exc}") from None


def _value(values: np.ndarray, shape: tuple[int, ...]) -> Any:
    return float(values[0]) if shape == () else np.asarray(values).reshape(shape).tolist()
