"""Scenario files: YAML in, a validated World out.

Validation happens before t=0 and collects every problem (file, line, field, and the closest valid
name for a misspelt one) into one `ScenarioError`. See ``scenarios/`` for examples and the README
for the full shape.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from ..kernel.errors import DynabrainError, Problem, ScenarioError, UnitError
from ..kernel.module import Module
from ..kernel.plugins import resolve_core
from ..kernel.suggest import did_you_mean
from ..kernel.units import parse_duration_ns
from ..kernel.world import World, as_connection
from ..kernel.yamlsrc import Path, YamlSource
from .events import EVENT_KINDS, EventCfg, build_event
from .expect import Expectation, check_names
from .make import ModuleSpecError, make_module
from .scene import parse_scene


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True)


class WorldCfg(_Strict):
    step: str | int | float = "2ms"
    """Base step (a duration; ``2ms``)."""
    duration: str | int | float = "1s"
    """How long `dynabrain run` simulates."""
    core: str | None = "mujoco"
    """Physics engine: ``mujoco`` or ``exudyn`` (None for a world of signal modules only)."""
    seed: int = 0
    history: int = 1000
    """How many ticks `backtick` can go back."""
    realtime: bool | float = False


class ModuleCfg(_Strict):
    name: str
    python: str | None = None
    """``package.module:Class``."""
    fmu: str | None = None
    """An FMU: a ``.fmu`` file or a source folder under ``fmus/`` (built on first use)."""
    isolate: bool = False
    """Run the FMU in a process of its own (a crash is reported, not fatal)."""
    call_timeout: str | int | float | None = None
    """With ``isolate``: how long one FMU call may take before its process is killed (default 30 s)."""
    params: dict[str, Any] = {}
    period: str | int | float | None = None
    targets: list[str] = []
    connect: list[list[Any]] = []


class ExpectCfg(_Strict):
    that: str
    at: str | int | float | None = None
    """When to check (a duration); default: the end of the run."""
    during: list[str | int | float] | None = None
    """``[from, to]``: check at every tick in between."""
    name: str | None = None


class LogCfg(_Strict):
    mcap: str | None = None
    decimate: int = 1


class ScenarioModel(_Strict):
    name: str
    description: str = ""
    world: WorldCfg = WorldCfg()
    scene: list[dict[str, Any]] | dict[str, Any] = []
    core: dict[str, Any] = {}
    """Parameters of the physics core (``friction``, ``restitution``, ``gravity``, ``substeps``)."""
    select: list[str] | None = None
    modules: list[ModuleCfg] = []
    connect: list[list[Any]] = []
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

    @property
    def dir(self) -> str:
        return os.path.dirname(os.path.abspath(self.path))

    def build(self, **overrides: Any) -> World:
        """A World ready at t=0, or a `ScenarioError` listing every problem."""
        self.expectations = []
        builder = _Builder(self)
        world = builder.build(overrides)
        if builder.problems:
            world.close()
            raise ScenarioError(builder.problems)
        world.module_factory = functools.partial(make_module, base_dir=self.dir)
        world.rebuild = functools.partial(load_world, os.path.abspath(self.path), **overrides)
        return world

    def check(self) -> list[Problem]:
        """Every problem `build()` would find (empty when the scenario is valid)."""
        try:
            self.build().close()
        except ScenarioError as exc:
            return exc.problems
        return []


def load_scenario(path: str | os.PathLike[str]) -> Scenario:
    """Read and validate the shape of a scenario file (the rest is checked by `Scenario.build`)."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as exc:
        raise ScenarioError([Problem(f"cannot read the scenario: {exc.strerror}", path)]) from None
    source = YamlSource(text, path)
    if source.problems:
        raise ScenarioError(source.problems)
    if not isinstance(source.data, dict):
        raise ScenarioError([Problem("a scenario is a mapping (name:, world:, scene:, ...)", path, 1)])
    problems = list(source.problems)
    try:
        model = ScenarioModel.model_validate(source.data)
    except ValidationError as exc:
        problems += [_pydantic_problem(source, err) for err in exc.errors()]
        raise ScenarioError(problems) from None
    scenario = Scenario(path, source, model)
    try:
        scenario.duration_ns = parse_duration_ns(model.world.duration)
    except UnitError as exc:
        problems.append(source.problem(("world", "duration"), str(exc)))
    if problems:
        raise ScenarioError(problems)
    return scenario


def load_world(path: str | os.PathLike[str], **overrides: Any) -> World:
    """The World a scenario file describes, ready at t=0 (``overrides`` replace ``world:`` keys, e.g.
    ``history=100``); a `ScenarioError` lists every problem at once."""
    return load_scenario(path).build(**overrides)


_MODELS = {"": ScenarioModel, "world": WorldCfg, "modules": ModuleCfg, "expect": ExpectCfg, "log": LogCfg,
           "events": EventCfg}


def _pydantic_problem(source: YamlSource, err: dict[str, Any]) -> Problem:
    loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and "[" in p))
    if err["type"] == "extra_forbidden":
        section = next((p for p in reversed(loc[:-1]) if isinstance(p, str)), "")
        model = _MODELS.get(section, ScenarioModel if len(loc) == 1 else None)
        known = list(model.model_fields) if model is not None else []
        if section == "events":
            known += list(EVENT_KINDS)
        return source.problem(loc, f"unknown key {loc[-1]!r}" + did_you_mean(str(loc[-1]), known)
                              + (f"; valid keys: {', '.join(known)}" if known else ""))
    message = err["msg"].removeprefix("Value error, ")
    return source.problem(loc, message)


class _Builder:
    """Builds a World from a Scenario, collecting every problem instead of stopping at the first."""

    def __init__(self, scenario: Scenario):
        self.sc = scenario
        self.src = scenario.source
        self.problems: list[Problem] = []
        self.later_modules: set[str] = set()
        """Modules the scenario's events add (their names may be used before they exist)."""

    def report(self, path: Path, message: str) -> None:
        self.problems.append(self.src.problem(path, message))

    def build(self, overrides: dict[str, Any]) -> World:
        m = self.sc.model
        cfg = m.world.model_copy(update=overrides)
        try:
            step = parse_duration_ns(cfg.step)
        except UnitError as exc:
            self.report(("world", "step"), str(exc))
            step = 2_000_000
        if self.sc.duration_ns % step:
            self.report(("world", "duration"), f"duration is not a whole number of {cfg.step} steps")
        world = World(m.name, step=step, seed=cfg.seed, history=cfg.history)
        self._add_core(world, cfg)
        self._add_modules(world)
        self._connect(world, m.connect, ("connect",))
        self._select(world)
        self._events(world)
        self._expectations(world)
        return world

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
        scene, scene_problems = parse_scene(m.scene, self.src, self.sc.dir, cfg.core)
        self.problems += scene_problems
        if scene_problems:
            return
        try:
            core = cls("core", scene, scenario_dir=self.sc.dir, **m.core)
            world.add_module(core)
        except DynabrainError as exc:
            self.report(("core",) if "parameter" in str(exc) else ("scene",), str(exc))

    def _add_modules(self, world: World) -> None:
        for i, cfg in enumerate(self.sc.model.modules):
            module = self.make_module(cfg, ("modules", i))
            if module is None:
                continue
            try:
                world.add_module(module, period=_period(cfg.period))
            except DynabrainError as exc:
                self.report(("modules", i), str(exc))
                continue
            self._connect(world, cfg.connect, ("modules", i, "connect"))

    def make_module(self, cfg: ModuleCfg, path: Path) -> Module | None:
        """The module ``cfg`` describes (see `make.make_module`), or None with the problem reported."""
        try:
            return make_module(cfg, base_dir=self.sc.dir)
        except ModuleSpecError as exc:
            self.report(path if exc.field is None else (*path, exc.field), str(exc))
            return None

    def _connect(self, world: World, items: list[list[Any]], path: Path) -> None:
        for j, item in enumerate(items):
            try:
                conn = as_connection(item)
                world.connect(conn.src, conn.dst, delay=conn.delay)
            except DynabrainError as exc:
                self.report((*path, j), str(exc))

    def _select(self, world: World) -> None:
        if self.sc.model.select is None or world.core is None:
            return
        try:
            world.make(self.sc.model.select)
        except DynabrainError as exc:
            self.report(("select",), str(exc))

    def _events(self, world: World) -> None:
        events = sorted(enumerate(self.sc.model.events), key=lambda item: parse_duration_ns(item[1].at)
                        if _is_duration(item[1].at) else 0)
        for i, ev in events:
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
            try:
                if cfg.during is not None:
                    if len(cfg.during) != 2:
                        raise UnitError("during is [from, to]")
                    start, stop = (parse_duration_ns(v) // world.dt_ns for v in cfg.during)
                else:
                    start = stop = end if cfg.at is None else parse_duration_ns(cfg.at) // world.dt_ns
                if not 0 <= start <= stop <= end:
                    raise UnitError(f"expectation time is outside the run (0 .. {self.sc.model.world.duration})")
                exp = Expectation(cfg.that, start, stop, cfg.name or cfg.that, self.src.line(path))
            except DynabrainError as exc:
                self.report(path, str(exc))
                continue
            core_failed = self.sc.model.world.core is not None and world.core is None
            for message in () if core_failed else check_names(exp, world, self.later_modules):
                self.report((*path, "that"), message)  # (with no core, body names cannot be checked)
            self.sc.expectations.append(exp)


def _is_duration(value: Any) -> bool:
    try:
        parse_duration_ns(value)
    except DynabrainError:
        return False
    return True


def _period(value: Any) -> int | None:
    return None if value is None else parse_duration_ns(value)
