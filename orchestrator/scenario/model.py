"""Scenario files: YAML in, a validated World out.

Validation happens before t=0 and collects every problem (file, line, field, and the closest valid
name for a misspelt one) into one `ScenarioError`. See ``scenarios/`` for examples and
``docs/scenarios.md`` for the full shape.
"""

from __future__ import annotations

import copy
import functools
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..kernel.errors import DynabrainError, Problem, ScenarioError, UnitError
from ..kernel.history import format_bytes, projected_state_bytes
from ..kernel.module import Module
from ..kernel.plugins import ClassPolicy, resolve_core, resolve_module_class
from ..kernel.suggest import did_you_mean
from ..kernel.units import format_duration, parse_duration_ns
from ..kernel.world import World, as_connection
from ..kernel.yamlsrc import Path, YamlSource, read_yaml
from . import limits
from .events import EVENT_KINDS, EventCfg, Timeline, build_event
from .expect import Expectation, check_names
from .limits import (
    CORE_LIMITS,
    ByteSize,
    Duration,
    Name,
    PositiveDuration,
    Realtime,
    check_magnitudes,
    param_problem,
    short,
)
from .make import ModuleSpecError, make_module
from .scene import parse_scene


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True)


class WorldCfg(_Strict):
    step: PositiveDuration = "2ms"
    """Base step (a duration; ``2ms``)."""
    duration: PositiveDuration = "1s"
    """How long `dynabrain run` simulates."""
    core: str | None = "mujoco"
    """Physics engine: ``mujoco`` or ``exudyn`` (None for a world of signal modules only)."""
    seed: Annotated[int, Field(strict=True, ge=0, le=2**63 - 1)] = 0
    history: Annotated[int, Field(strict=True, ge=0)] = 1000
    """How many ticks `backtick` can go back."""
    keyframe_every: Annotated[int, Field(strict=True, ge=1)] = 2
    """History keeps a whole state every this many ticks (and after each edit or event), and steps the
    ticks between again when a backtick goes to one: 1 keeps a state every tick (`World`'s docstring
    says what each costs)."""
    history_budget: ByteSize | None = None
    """The most memory the history may hold when full (``2GiB``, ``25%``); default: `kernel.history.default_budget`."""
    realtime: Realtime = False
    start_time: Duration | None = None
    """The FMUs' time at the start (``2s``): every FMU module starts there (its own ``DefaultExperiment
    startTime`` overridden) unless its entry gives ``start_time``. The world's clock (ticks, ``at:``,
    ``during:``, ``duration``, the log) still counts from 0 at the start: an FMU's time is the world's
    plus its start time."""


class ModuleCfg(_Strict):
    name: Name
    python: str | None = None
    """``package.module:Class``."""
    fmu: str | None = None
    """An FMU: a ``.fmu`` file or a source folder under ``fmus/`` (built on first use)."""
    isolate: Annotated[bool, Field(strict=True)] = False
    """Run the FMU in a process of its own (a crash is reported, not fatal)."""
    call_timeout: str | int | float | None = None
    """With ``isolate``: how long one FMU call may take before its process is killed (default 30 s)."""
    params: dict[str, Any] = {}
    start_time: Duration | None = None
    """An FMU's time at the start (``1.5s``), instead of its ``DefaultExperiment startTime`` and of
    ``world.start_time``."""
    period: PositiveDuration | None = None
    targets: list[str] = []
    connect: list[list[Any]] = []


class IterateCfg(_Strict):
    """A loop of feedthrough modules stepped again until its values agree (`World.iterate`)."""

    name: Name | None = None
    modules: Annotated[list[Name], Field(min_length=1)]
    """The loop's modules, in the order they step."""
    tolerance: Annotated[float, Field(gt=0)] = 1e-9
    max_iterations: Annotated[int, Field(strict=True, ge=1)] = 50


class ExpectCfg(_Strict):
    that: str
    at: Duration | None = None
    """When to check (a duration); default: the end of the run."""
    during: Annotated[list[Duration], Field(min_length=2, max_length=2)] | None = None
    """``[from, to]``: check at every tick in between."""
    name: str | None = None


class LogCfg(_Strict):
    mcap: str | None = None
    decimate: Annotated[int, Field(strict=True, ge=1)] = 1
    ros2_schemas: Annotated[bool, Field(strict=True)] = False
    """Also write /clock, /joint_states and /tf as ROS 2 messages (CDR, ros2msg schemas); ``--ros2-schemas``."""


class ScenarioModel(_Strict):
    name: Name
    description: str = ""
    world: WorldCfg = WorldCfg()
    scene: Any = []
    """A list of shapes or ``{model: file}``, checked by `parse_scene`."""
    core: dict[str, Any] = {}
    """Parameters of the physics core (``friction``, ``restitution``, ``gravity``, ``substeps``)."""
    select: list[str] | None = None
    modules: list[ModuleCfg] = []
    connect: list[list[Any]] = []
    iterate: list[IterateCfg] = []
    """Loops with direct feedthrough whose macro steps are iterated to agreement (strong coupling)."""
    events: list[EventCfg] = []
    expect: list[ExpectCfg] = []
    log: LogCfg = LogCfg()


@dataclass
class Scenario:
    """A parsed scenario. `build()` validates it fully and returns a World."""

    path: str
    source: YamlSource
    model: ScenarioModel
    duration_ns: int = 0
    expectations: list[Expectation] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)
    """Problems found while reading the file (its shape); `build` reports them with its own."""
    invalid: frozenset[Path] = frozenset()
    """Items (``("modules", 2)``) whose shape is wrong: `build` leaves them out."""
    allow_python: tuple[str, ...] = ()
    """Packages whose module classes the user allowed (``--allow-python``) besides dynabrain's own, the
    registered ones and the scenario folder's own modules (`plugins.ClassPolicy`)."""
    local_modules: bool = True
    """Whether modules in the scenario's folder may be named (`replay --verify` allows them only when the
    recorded scenario is still there, as recorded: a log's claim of a folder is not enough)."""

    @property
    def dir(self) -> str:
        return os.path.dirname(os.path.abspath(self.path))

    def build(self, **overrides: Any) -> World:
        """A World ready at t=0, or a `ScenarioError` listing every problem."""
        self.expectations = []
        builder = _Builder(self)
        factory = functools.partial(make_module, base_dir=self.dir, allow_python=self.allow_python,
                                    local_modules=self.local_modules)
        rebuild = functools.partial(load_world, os.path.abspath(self.path), allow_python=self.allow_python,
                                    **overrides)
        world = builder.build(overrides, factory, rebuild)
        problems = _in_order([*self.problems, *builder.problems])
        if problems:
            world.close()
            raise ScenarioError(problems)
        return world

    def check(self) -> list[Problem]:
        """Every problem `build()` would find (empty when the scenario is valid)."""
        try:
            self.build().close()
        except ScenarioError as exc:
            return exc.problems
        return []


def load_scenario(path: str | os.PathLike[str], allow_python: Sequence[str] = ()) -> Scenario:
    """Read and validate the shape of a scenario file (the rest is checked by `Scenario.build`). A
    file whose shape is wrong is built all the same, leaving out what is wrong, so that the
    `ScenarioError` lists every problem of the file, not only the first kind found. ``allow_python``:
    see `Scenario.allow_python`."""
    path = os.fspath(path)
    source = read_yaml(path, "the scenario")
    if source.problems and source.data is None:
        raise ScenarioError(source.problems)
    if not isinstance(source.data, dict):
        shape = Problem("a scenario is a mapping (name:, world:, scene:, ...)", path, 1)
        raise ScenarioError([*source.problems, shape])
    model, problems, invalid = _validate(source)
    scenario = Scenario(path, source, model, problems=[*source.problems, *problems], invalid=frozenset(invalid),
                        allow_python=tuple(allow_python))
    scenario.duration_ns = parse_duration_ns(model.world.duration)
    if scenario.problems:
        scenario.build().close()  # raises, with the problems of the shape and those the build finds
    return scenario


def load_world(path: str | os.PathLike[str], *, allow_python: Sequence[str] = (), **overrides: Any) -> World:
    """The World a scenario file describes, ready at t=0 (``overrides`` replace ``world:`` keys, e.g.
    ``history=100``; ``allow_python``: see `Scenario.allow_python`); a `ScenarioError` lists every
    problem at once. A name with no such file here is a shipped example's (``load_world("two_cubes")``,
    as ``dynabrain run two_cubes``)."""
    import pathlib

    from .shipped import resolve_scenario

    return load_scenario(resolve_scenario(pathlib.Path(os.fspath(path))), allow_python).build(**overrides)


def _in_order(problems: list[Problem]) -> list[Problem]:
    """Each problem once, in the order of the file's lines (problems without a line first)."""
    unique = list(dict.fromkeys(problems))
    return sorted(unique, key=lambda p: p.line or 0)


# -- the shape: pydantic, every problem, and a model built from what is left ------------------------------
_MODELS = {"": ScenarioModel, "world": WorldCfg, "modules": ModuleCfg, "expect": ExpectCfg, "log": LogCfg,
           "events": EventCfg}
_ITEMS = {"modules": ModuleCfg, "events": EventCfg, "expect": ExpectCfg, "connect": None}
"""Sections that are lists of items: a wrong item is left out (`Scenario.invalid`), the rest is built."""
_PLACEHOLDER: dict[str, Any] = {"modules": {"name": "?"}, "events": {"at": 0}, "expect": {"that": "True"},
                                "connect": []}


def _validate(source: YamlSource) -> tuple[ScenarioModel, list[Problem], set[Path]]:
    """The scenario's model, every problem of its shape, and the items left out. What is wrong is
    taken out of a copy of the data (a key dropped, so its default applies, or an item replaced by
    a placeholder that the build leaves out) until the rest validates."""
    data = source.data
    problems: list[Problem] = []
    invalid: set[Path] = set()
    for _ in range(20):
        try:
            return ScenarioModel.model_validate(data), problems, invalid
        except ValidationError as exc:
            if data is source.data:
                data = copy.deepcopy(data)
            groups: dict[Path, list[Any]] = {}
            for err in exc.errors():
                groups.setdefault(_existing(data, tuple(err["loc"])), []).append(err)
            unreadable = {p.field for p in source.problems}
            for loc, errors in groups.items():
                if source.field(loc) not in unreadable:  # (a value the reader could not make is None here)
                    problems.append(_pydantic_problem(source, data, loc, errors))
            for loc, errors in groups.items():
                _take_out(data, loc, errors, invalid)
    raise ScenarioError(problems)  # not reached: every round takes something out


def _existing(data: Any, loc: tuple[Any, ...]) -> Path:
    """The longest start of pydantic's ``loc`` that is a path in ``data`` (pydantic adds the names of
    union members and validators, and a missing key is not in the data)."""
    out: list[str | int] = []
    for part in loc:
        in_dict = isinstance(data, dict) and isinstance(part, str) and part in data
        if not (in_dict or (isinstance(data, list) and isinstance(part, int) and 0 <= part < len(data))):
            break
        data = data[part]
        out.append(part)
    return tuple(out)


def _at(data: Any, path: Path) -> Any:
    for part in path:
        data = data[part]
    return data


def _pydantic_problem(source: YamlSource | _Shifted, data: Any, loc: Path, errors: list[Any],
                      model: type[BaseModel] | None = None) -> Problem:
    """One problem for pydantic's ``errors`` at ``loc`` (several, for a value no member of a union takes).
    ``model``: the model that holds an unknown key, when its section's name does not say."""
    extra = [e for e in errors if e["type"] == "extra_forbidden"]
    if extra:
        section = next((p for p in reversed(loc[:-1]) if isinstance(p, str)), "")
        if model is None:
            model = _MODELS.get(section, ScenarioModel if len(loc) == 1 else None)
        known = list(model.model_fields) if model is not None else []
        if section == "events":
            known += [k for k in EVENT_KINDS if k not in known]
        return source.problem(loc, f"unknown key {short(loc[-1])}" + did_you_mean(str(loc[-1]), known)
                              + (f"; valid keys: {', '.join(known)}" if known else ""))
    missing = [str(e["loc"][len(loc)]) for e in errors if e["type"] == "missing" and len(e["loc"]) > len(loc)]
    if missing:
        return source.problem(loc, "missing " + ", ".join(repr(m) for m in dict.fromkeys(missing)))
    messages = list(dict.fromkeys(e["msg"].removeprefix("Value error, ") for e in errors))
    value = _at(data, loc)
    own = all(e["type"] == "value_error" for e in errors)  # our validators' messages say what they got
    got = "" if own or any(short(value) in m for m in messages) else f" (got {short(value)})"
    return source.problem(loc, " or ".join(messages) + got)


def _take_out(data: Any, loc: Path, errors: list[Any], invalid: set[Path]) -> None:
    """Take what is wrong at ``loc`` out of ``data`` (see `_validate`)."""
    if _existing(data, loc) != loc or any(loc[:n] in invalid for n in range(1, len(loc) + 1)):
        return  # taken out already, with what held it
    if len(loc) >= 2 and loc[0] in _ITEMS and isinstance(loc[1], int):
        item = _ITEMS[loc[0]]
        key = loc[2] if len(loc) >= 3 else None
        optional = item is not None and isinstance(key, str) and (
            key not in item.model_fields or not item.model_fields[key].is_required())
        if optional and loc[0] != "events":  # drop the key, keep checking the rest of the item
            del data[loc[0]][loc[1]][key]
        else:
            data[loc[0]][loc[1]] = copy.deepcopy(_PLACEHOLDER[loc[0]])
            invalid.add(loc[:2])
        return
    if not loc:
        for err in errors:  # a required key missing at the top
            if err["type"] == "missing" and len(err["loc"]) == 1:
                data[err["loc"][0]] = "?"
        return
    parent = _at(data, loc[:-1])
    if isinstance(parent, dict):
        if loc == ("name",):
            parent["name"] = "?"
        else:
            del parent[loc[-1]]
    else:  # an element of a list that is not a section's item (select: [...]): drop the whole list
        _take_out(data, loc[:-1], [], invalid)


class _Builder:
    """Builds a World from a Scenario, collecting every problem instead of stopping at the first."""

    def __init__(self, scenario: Scenario):
        self.sc = scenario
        self.src = scenario.source
        self.problems: list[Problem] = []
        self.later_modules: set[str] = set()
        """Modules the scenario's events add (their names may be used before they exist)."""
        self.timeline = Timeline(set(), {})
        """The structure as the events checked so far leave it."""

    def report(self, path: Path, message: str) -> None:
        self.problems.append(self.src.problem(path, message))

    def report_validation(self, path: Path, exc: ValidationError, model: type[BaseModel]) -> None:
        """Report the pydantic errors of a part validated late (an event's ``add``, a ``model``), under ``path``."""
        data = _at(self.src.data, path)
        groups: dict[Path, list[Any]] = {}
        for err in exc.errors():
            groups.setdefault(_existing(data, tuple(err["loc"])), []).append(err)
        for loc, errors in groups.items():
            self.problems.append(_pydantic_problem(_Shifted(self.src, path), data, loc, errors,
                                                   model if len(loc) == 1 else None))

    def build(self, overrides: dict[str, Any], module_factory: Callable[[dict[str, Any]], Any] | None = None,
              rebuild: Callable[[], World] | None = None) -> World:
        m = self.sc.model
        cfg = self._world_cfg(overrides)
        step = parse_duration_ns(cfg.step)
        if self.sc.duration_ns % step:
            self.report(("world", "duration"), f"the duration ({format_duration(self.sc.duration_ns)}) is not a "
                                               f"whole number of {cfg.step} steps")
        world = World(m.name, step=step, seed=cfg.seed, history=cfg.history, keyframe_every=cfg.keyframe_every,
                      module_factory=module_factory, rebuild=rebuild)
        if cfg.history_budget is not None:
            world.history.budget = cfg.history_budget
        self._add_core(world, cfg)
        self._add_modules(world)
        self._iterate(world)
        for items, path in self._module_connects:
            self._connect(world, items, path)
        self._connect(world, m.connect, ("connect",))
        self._history_memory(world)
        self._select(world)
        self._events(world)
        self._expectations(world)
        return world

    def _world_cfg(self, overrides: dict[str, Any]) -> WorldCfg:
        """``world:`` with ``overrides`` (given to `build`, not in the file) checked like the file's keys."""
        if not overrides:
            return self.sc.model.world
        try:
            return WorldCfg.model_validate({**self.sc.model.world.model_dump(exclude_unset=True), **overrides})
        except ValidationError as exc:
            for err in exc.errors():
                self.problems.append(Problem(f"{err['msg'].removeprefix('Value error, ')} (an override given to "
                                             f"build: {short(overrides)})", self.src.file, None,
                                             "world." + ".".join(map(str, err["loc"][:1]))))
            return self.sc.model.world

    def _add_core(self, world: World, cfg: WorldCfg) -> None:
        m = self.sc.model
        if cfg.core is None:
            if m.scene:
                self.report(("scene",), "a scene needs a physics core (world.core)")
            return
        try:
            cls = resolve_core(cfg.core)
        except DynabrainError as exc:
            self.report(("world", "core"), str(exc))
            return
        too_many = limits.too_many_bodies(limits.scene_bodies(m.scene))  # (before a body is made)
        if too_many:
            self.report(("scene",), too_many)
            return
        scene, scene_problems = parse_scene(m.scene, self.src, self.sc.dir, cfg.core)  # (a model file counted)
        self.problems += scene_problems
        params = self._core_params(cls)
        if scene_problems:
            return
        try:
            core = cls("core", scene, scenario_dir=self.sc.dir, **params)
            world.add_module(core)
        except DynabrainError as exc:
            self.report(("core",) if "parameter" in str(exc) else ("scene",), str(exc))
        except (ValueError, ArithmeticError) as exc:  # the engine's library refusing the scene (a model file
            # it cannot read: MuJoCo's XML errors are ValueErrors); anything else is a bug, and shows as one
            self.report(("scene",), f"the {cfg.core} core cannot load the scene: {type(exc).__name__}: {exc}")

    def _history_memory(self, world: World) -> None:
        """Refuse a history whose memory when full, projected from the modules, is above its budget,
        naming the module that makes a state large when one does."""
        try:
            sizes = projected_state_bytes(world.modules.values())
            per_state = sum(sizes.values())
            name, largest = max(sizes.items(), key=lambda item: item[1])
            what = f"; the module {name!r} holds {format_bytes(largest)} of each" if 2 * largest > per_state else ""
            world.history.check(per_state, what)
        except DynabrainError as exc:
            self.report(("world", "history"), str(exc))

    def _core_params(self, cls: type) -> dict[str, Any]:
        """The ``core:`` parameters whose values are good (the others are reported and left out)."""
        specs = cls.param_specs()
        good = {}
        for key, value in self.sc.model.core.items():
            if key in specs:
                problem = param_problem(specs[key], value, CORE_LIMITS.get(key))
                if problem:
                    self.report(("core", key), f"core parameter {key!r}: {problem}")
                    continue
            good[key] = value
        return good

    def _add_modules(self, world: World) -> None:
        """Add the modules; their own ``connect:`` lists are made after the ``iterate:`` loops are
        declared (`_iterate`), as a loop must be before the connections that close it."""
        self._module_connects: list[tuple[list[list[Any]], Path]] = []
        for i, cfg in enumerate(self.sc.model.modules):
            if ("modules", i) in self.sc.invalid:
                continue
            module = self.make_module(cfg, ("modules", i))
            if module is None:
                continue
            try:
                world.add_module(module, period=_period(cfg.period))
            except DynabrainError as exc:
                self.report(("modules", i), str(exc))
                continue
            self._module_connects.append((cfg.connect, ("modules", i, "connect")))

    def make_module(self, cfg: ModuleCfg, path: Path) -> Module | None:
        """The module ``cfg`` describes (see `make.make_module`), or None with the problem reported. A
        parameter whose value is wrong (type, unit, finiteness, `limits.MAX_MAGNITUDE`) is reported and
        left out, so that the module is still made and what uses it is still checked."""
        params = self._good_params(cfg, path)
        update: dict[str, Any] = {} if params is None else {"params": params}
        start = self.sc.model.world.start_time
        if start is not None and cfg.fmu is not None and cfg.start_time is None:
            update["start_time"] = start  # the world's start time, for an FMU that gives none of its own
        try:
            module = make_module(cfg.model_copy(update=update) if update else cfg, base_dir=self.sc.dir,
                                 allow_python=self.sc.allow_python, local_modules=self.sc.local_modules)
        except ModuleSpecError as exc:
            self.report(path if exc.field is None else (*path, exc.field), str(exc))
            return None
        too_large = _port_values_problem(module)
        if too_large:
            module.close()
            self.report((*path, "params") if cfg.params else path, f"module {cfg.name!r}: {too_large}")
            return None
        for key in cfg.params if params is None else ():  # (an FMU's parameters are known once it is made)
            try:
                check_magnitudes(module.params.get(key), f"parameter {key!r}")
            except UnitError as exc:
                self.report((*path, "params", key), f"module {cfg.name!r}: {exc}")
        return module

    def _good_params(self, cfg: ModuleCfg, path: Path) -> dict[str, Any] | None:
        """``cfg.params`` without the values its class's parameters refuse, each reported; None when the
        class declares its parameters only once made (an FMU) or cannot be found (`make_module` says why)."""
        if cfg.python is None or cfg.fmu is not None:
            return None
        try:  # (a class the policy refuses is not imported: make_module says why)
            folders = [self.sc.dir] if self.sc.local_modules else []
            cls = resolve_module_class(cfg.python, ClassPolicy.of(self.sc.allow_python, folders))
            specs = cls.param_specs() if isinstance(cls, type) and issubclass(cls, Module) else None
        except Exception:  # make_module reports a class it cannot find or use
            return None
        if not isinstance(specs, dict):
            return None
        good = {}
        for key, value in cfg.params.items():
            problem = param_problem(specs[key], value) if key in specs else None
            if problem:
                self.report((*path, "params", key), f"module {cfg.name!r}, parameter {key!r}: {problem}")
            else:
                good[key] = value
        return good

    def _connect(self, world: World, items: list[list[Any]], path: Path) -> None:
        for j, item in enumerate(items):
            if (*path, j) in self.sc.invalid:
                continue
            try:
                conn = as_connection(item)
                world.connect(conn.src, conn.dst, delay=conn.delay)
            except DynabrainError as exc:
                self.report((*path, j), str(exc))

    def _iterate(self, world: World) -> None:
        """Declare the ``iterate:`` loops, before the connections that close them."""
        for j, loop in enumerate(self.sc.model.iterate):
            if ("iterate", j) in self.sc.invalid:
                continue
            try:
                world.iterate(loop.modules, name=loop.name, tolerance=loop.tolerance,
                              max_iterations=loop.max_iterations)
            except DynabrainError as exc:
                self.report(("iterate", j), str(exc))

    def _select(self, world: World) -> None:
        if self.sc.model.select is None or world.core is None:
            return
        try:
            world.make(self.sc.model.select)
        except DynabrainError as exc:
            self.report(("select",), str(exc))

    def _events(self, world: World) -> None:
        self.timeline = Timeline.of(world)
        valid = [(i, ev) for i, ev in enumerate(self.sc.model.events) if ("events", i) not in self.sc.invalid]
        for i, ev in sorted(valid, key=lambda item: parse_duration_ns(item[1].at)):
            path: Path = ("events", i)
            try:
                action, label = build_event(ev, world, self, path)
                world.at(parse_duration_ns(ev.at), label, action)
            except DynabrainError as exc:
                self.report(path, str(exc))

    def _expectations(self, world: World) -> None:
        end = self.sc.duration_ns // world.dt_ns
        for i, cfg in enumerate(self.sc.model.expect):
            path: Path = ("expect", i)
            if path in self.sc.invalid:
                continue
            try:
                if cfg.during is not None:
                    start, stop = (parse_duration_ns(v) // world.dt_ns for v in cfg.during)
                else:
                    start = stop = end if cfg.at is None else parse_duration_ns(cfg.at) // world.dt_ns
                if not 0 <= start <= stop <= end:
                    raise UnitError(f"expectation time is outside the run (0 .. "
                                    f"{format_duration(self.sc.duration_ns)})")
            except DynabrainError as exc:
                self.report((*path, "during" if cfg.during is not None else "at"), str(exc))
                continue
            try:
                exp = Expectation(cfg.that, start, stop, cfg.name or cfg.that, self.src.line(path))
            except DynabrainError as exc:
                self.report((*path, "that"), str(exc))
                continue
            core_failed = self.sc.model.world.core is not None and world.core is None
            for message in () if core_failed else check_names(exp, world, self.later_modules):
                self.report((*path, "that"), message)  # (with no core, body names cannot be checked)
            self.sc.expectations.append(exp)


class _Shifted:
    """A `YamlSource` seen from inside one of its values: paths are relative to ``base``."""

    def __init__(self, source: YamlSource, base: Path):
        self.source, self.base = source, base

    def problem(self, path: Path, message: str) -> Problem:
        return self.source.problem((*self.base, *path), message)


def _port_values_problem(module: Module) -> str | None:
    """What is wrong with the size of ``module``'s ports (`limits.MAX_PORT_VALUES`), or None; ports a
    module declares only once it joins a world are counted then, by the kernel."""
    try:
        ports = [*module.inputs(), *module.outputs()]
        values = sum(math.prod(p.shape) for p in ports if getattr(p, "view_of", None) is None)
    except Exception:  # (ports that need the world; the module's own errors show when it is added)
        return None
    if values <= limits.MAX_PORT_VALUES:
        return None
    return f"its ports hold {values} numbers, more than {limits.MAX_PORT_VALUES} (MAX_PORT_VALUES)"


def _period(value: Any) -> int | None:
    return None if value is None else parse_duration_ns(value)
