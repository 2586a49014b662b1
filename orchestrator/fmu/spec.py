"""``fmu.yaml``: the declaration of a C FMU in a source folder (what `dynabrain fmu build` reads).

```yaml
name: servo                  # the model identifier (a C identifier)
description: PD joint servos
fmi: [2, 3]                  # FMI versions to build; the first is the default
defines: {N: 2}              # C constants, usable as sizes
variables:
  - {name: q_ref, causality: input, size: N, unit: rad, description: target angles}
  - {name: tau, causality: output, size: N, unit: N*m, depends: [q_ref]}
  - {name: kp, causality: parameter, variability: tunable, start: 50.0}
  - {name: torque, causality: local, size: N}          # state the model keeps
  - {name: mode, type: enumeration, causality: input, items: [off, hold, track], start: hold}
  - {name: label, type: string, causality: parameter, start: "servo A", capacity: 64}
c_state:                     # extra C fields of ModelData (for example a generator's state)
  - {name: rng, ctype: uint64_t}
```

Every problem is reported at once, with file, line and field (a `FMUBuildError`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, ValidationError

from ..kernel.errors import Problem
from ..kernel.yamlsrc import YamlSource, read_yaml
from .errors import FMUBuildError

IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
VarType = Literal["real", "float32", "int8", "uint8", "int16", "uint16", "integer", "uint32", "int64", "uint64",
                  "boolean", "enumeration", "string", "binary"]
FMI1_TYPES = ("real", "integer", "boolean", "string")
"""The types an FMI 1.0 build takes."""
FMI3_ONLY = ("float32", "int8", "uint8", "int16", "uint16", "uint32", "int64", "uint64", "binary")
"""Types FMI 2.0 does not have."""
INT_RANGES = {"int8": (-2**7, 2**7 - 1), "uint8": (0, 2**8 - 1), "int16": (-2**15, 2**15 - 1),
              "uint16": (0, 2**16 - 1), "integer": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
              "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1)}
FLOATS = ("real", "float32")
TEXT = ("string", "binary")
DEFAULT_CAPACITY = 256
CTYPES = ("double", "float", "int32_t", "uint32_t", "int64_t", "uint64_t", "uint8_t", "int")
SPEC_FILE = "fmu.yaml"
RESERVED = {"time", "m", "h", "fmu_interval_", "fmu_interval_changed_"}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class VarCfg(_Strict):
    name: str
    type: VarType = "real"
    causality: Literal["input", "output", "parameter", "local"]
    variability: Literal["fixed", "tunable", "discrete", "continuous"] | None = None
    """Default: ``fixed`` for a parameter, ``continuous`` for a real, ``discrete`` otherwise."""
    size: int | str | None = None
    """A vector of this many values (a number or a name from ``defines``)."""
    start: float | int | bool | str | list[float | int | bool] | None = None
    """A number, a list of them (a vector), true or false; an enumeration's item (or its number, from 1);
    a string's text; a binary's bytes in hex (``"666f6f"``)."""
    unit: str | None = None
    description: str = ""
    depends: list[str] | None = None
    """For an output: the inputs it depends on directly (default: all of them)."""
    items: list[str] | None = None
    """An enumeration's items, numbered from 1."""
    capacity: int | None = None
    """A string's or binary's room in bytes (default 256; a string keeps one for its end)."""
    clock: str | None = None
    """FMI 3.0: the clock this variable belongs to (a clocked variable: set or changed at its ticks)."""


class ClockCfg(_Strict):
    """An FMI 3.0 clock: an input clock ticking every ``interval`` seconds from ``shift`` (time-based),
    an input clock without an interval (triggered: the master says when), or an output clock the
    model ticks (``fmu_tick``)."""

    name: str
    causality: Literal["input", "output"] = "input"
    interval: float | None = None
    shift: float = 0.0
    variability: Literal["tunable", "changing", "countdown"] | None = None
    """An input clock whose interval the model gives while it runs (``fmu_set_interval``), instead of
    a constant ``interval``: ``tunable`` (periodic; the model may change the interval at an event, the
    new one counted from there), ``changing`` (the model gives the next interval at each tick) or
    ``countdown`` (the model starts a countdown at an event; the clock ticks once when it runs out)."""
    description: str = ""


class CStateCfg(_Strict):
    name: str
    ctype: str
    size: int | str | None = None


class CapsCfg(_Strict):
    get_set_state: bool = True
    serialize: bool = True


class SpecCfg(_Strict):
    name: str
    description: str = ""
    version: str = "1.0"
    fmi: list[Literal[1, 2, 3]] = [2]
    defines: dict[str, int] = {}
    sources: list[str] | None = None
    """C files of the model (default: every ``*.c`` in the folder)."""
    cflags: list[str] = []
    step: float | None = None
    """The default communication step in seconds (DefaultExperiment)."""
    start_time: float | None = None
    """The FMU's time at the start of a simulation, in seconds (DefaultExperiment startTime)."""
    capabilities: CapsCfg = CapsCfg()
    variables: list[VarCfg]
    c_state: list[CStateCfg] = []
    clocks: list[ClockCfg] = []
    """FMI 3.0 clocks (the FMU then has event mode): the model implements ``model_clock``."""
    interface: Literal["co-simulation", "scheduled-execution"] = "co-simulation"
    """FMI 3.0: ``scheduled-execution`` declares that interface alone (the master activates each input
    clock's partition: ``model_clock``; no steps); it needs clocks."""


@dataclass(frozen=True)
class Clock:
    """A checked clock: ``interval`` None for a triggered one (or an output clock)."""

    name: str
    causality: str
    interval: float | None
    shift: float
    description: str
    variability: str | None = None
    """``tunable``, ``changing``, ``countdown`` (the model gives the interval), else None."""


@dataclass(frozen=True)
class Var:
    """One variable, checked: ``size`` is None for a scalar, ``start`` has one value per element (an
    enumeration's item number, a string's text, a binary's bytes)."""

    name: str
    type: str
    causality: str
    variability: str
    size: int | None
    size_expr: str | None
    start: tuple[float | int | bool, ...]
    start_given: bool
    unit: str | None
    description: str
    depends: tuple[str, ...] | None
    items: tuple[str, ...] = ()
    capacity: int = 0
    clock: str | None = None

    @property
    def count(self) -> int:
        return 1 if self.size is None else self.size


@dataclass(frozen=True)
class FmuSpec:
    """A checked fmu.yaml."""

    folder: Path
    name: str
    description: str
    version: str
    fmi: tuple[int, ...]
    defines: dict[str, int]
    sources: tuple[Path, ...]
    cflags: tuple[str, ...]
    step: float | None
    can_get_set: bool
    can_serialize: bool
    variables: tuple[Var, ...]
    c_state: tuple[tuple[str, str, str | None], ...]
    start_time: float | None = None
    clocks: tuple[Clock, ...] = ()
    scheduled: bool = False
    """FMI 3.0 scheduled execution instead of co-simulation."""


def load_spec(folder: str | Path) -> FmuSpec:
    """Read and check ``folder/fmu.yaml``; raises `FMUBuildError` listing every problem."""
    folder = Path(folder)
    path = folder / SPEC_FILE
    src = read_yaml(path, "the FMU declaration")
    if src.problems:
        raise _fail(src.problems)
    if not isinstance(src.data, dict):
        raise _fail([Problem("fmu.yaml is a mapping (name:, variables:, ...)", str(path), 1)])
    try:
        cfg = SpecCfg.model_validate(src.data)
    except ValidationError as exc:
        problems = [src.problem(tuple(e["loc"]), e["msg"].removeprefix("Value error, ")) for e in exc.errors()]
        raise _fail(problems) from None
    return _Checker(folder, src, cfg).check()


def _fail(problems: list[Problem]) -> FMUBuildError:
    return FMUBuildError(f"{len(problems)} problem(s) in the FMU declaration:\n"
                         + "\n".join(f"  - {p}" for p in problems))


class _Checker:
    def __init__(self, folder: Path, src: YamlSource, cfg: SpecCfg):
        self.folder, self.src, self.cfg = folder, src, cfg
        self.problems: list[Problem] = []

    def report(self, path: tuple, message: str) -> None:
        self.problems.append(self.src.problem(path, message))

    def check(self) -> FmuSpec:
        cfg = self.cfg
        if not IDENT.match(cfg.name):
            self.report(("name",), f"name {cfg.name!r} must be a C identifier (it names the binary)")
        for key in cfg.defines:
            if not IDENT.match(key):
                self.report(("defines", key), f"define {key!r} is not a C identifier")
        if not cfg.fmi or len(set(cfg.fmi)) != len(cfg.fmi):
            self.report(("fmi",), "fmi lists each version (1, 2, 3) once")
        variables = self._variables()
        clocks = self._clocks(variables)
        c_state = self._c_state({v.name for v in variables} | {c.name for c in clocks})
        sources = self._sources()
        if cfg.step is not None and not (cfg.step > 0 and math.isfinite(cfg.step)):
            self.report(("step",), "step must be a positive number of seconds")
        if cfg.start_time is not None and not math.isfinite(cfg.start_time):
            self.report(("start_time",), "start_time must be a finite number of seconds")
        if cfg.capabilities.serialize and not cfg.capabilities.get_set_state:
            self.report(("capabilities",), "serialize needs get_set_state")
        scheduled = cfg.interface == "scheduled-execution"
        if scheduled and (list(cfg.fmi) != [3] or not clocks):
            self.report(("interface",), "scheduled execution is FMI 3.0 with clocks: fmi: [3] and clocks:")
        if self.problems:
            raise _fail(self.problems)
        return FmuSpec(self.folder, cfg.name, cfg.description, cfg.version, tuple(cfg.fmi), dict(cfg.defines),
                       sources, tuple(cfg.cflags), cfg.step, cfg.capabilities.get_set_state,
                       cfg.capabilities.serialize, variables, c_state, cfg.start_time, clocks, scheduled)

    def _clocks(self, variables: tuple[Var, ...]) -> tuple[Clock, ...]:
        out: list[Clock] = []
        names = {v.name for v in variables}
        for i, c in enumerate(self.cfg.clocks):
            path = ("clocks", i)
            if not IDENT.match(c.name) or c.name in names or c.name in RESERVED:
                self.report((*path, "name"), f"clock name {c.name!r} must be a new C identifier")
            names.add(c.name)
            if c.interval is not None and not (c.interval > 0 and math.isfinite(c.interval)):
                self.report((*path, "interval"), "a clock's interval is a positive number of seconds")
            if c.causality == "output" and c.interval is not None:
                self.report((*path, "interval"), "an output clock ticks when the model says (fmu_tick): no interval")
            if not (math.isfinite(c.shift) and c.shift >= 0 and (c.interval is None or c.shift < c.interval)):
                self.report((*path, "shift"), "a clock's shift is from 0 up to its interval (seconds)")
            if c.variability is not None and (c.causality == "output" or c.interval is not None):
                self.report((*path, "variability"), f"a {c.variability} clock is an input clock whose interval the "
                            "model gives with fmu_set_interval: no interval here")
            if c.variability in ("changing", "countdown") and c.shift:
                self.report((*path, "shift"), f"a {c.variability} clock has no shift")
            out.append(Clock(c.name, c.causality, c.interval, c.shift, c.description, c.variability))
        if out and (1 in self.cfg.fmi or 2 in self.cfg.fmi):
            self.report(("clocks",), "clocks are FMI 3.0: build this FMU for FMI 3.0 only (fmi: [3])")
        known = {c.name for c in out}
        for i, v in enumerate(self.cfg.variables):
            if v.clock is not None and v.clock not in known:
                self.report(("variables", i, "clock"), f"{v.clock!r} is not a clock of this FMU (clocks:)")
            if v.clock is not None and i < len(variables) and variables[i].variability == "continuous":
                self.report(("variables", i, "variability"), "a clocked variable is discrete")
        return tuple(out)

    def _size(self, value: int | str | None, path: tuple) -> tuple[int | None, str | None]:
        if value is None:
            return None, None
        n = self.cfg.defines.get(value) if isinstance(value, str) else value
        if n is None:
            self.report(path, f"size {value!r} is neither a number nor a name in defines")
            return None, None
        if n < 1:
            self.report(path, f"size must be at least 1, got {n}")
            return None, None
        return n, value if isinstance(value, str) else None

    def _variables(self) -> tuple[Var, ...]:
        out: list[Var] = []
        seen: set[str] = set()
        for i, v in enumerate(self.cfg.variables):
            path = ("variables", i)
            if not IDENT.match(v.name) or v.name in RESERVED:
                self.report((*path, "name"), f"variable name {v.name!r} must be a C identifier other than "
                            f"{', '.join(sorted(RESERVED))}")
            if v.name in seen:
                self.report((*path, "name"), f"variable {v.name!r} is declared twice")
            seen.add(v.name)
            size, expr = self._size(v.size, (*path, "size"))
            variability = v.variability or self._default_variability(v)
            self._check_variability(v, variability, path)
            self._check_type(v, size, path)
            start = self._start(v, size, path)
            capacity = (v.capacity or DEFAULT_CAPACITY) if v.type in TEXT else 0
            out.append(Var(v.name, v.type, v.causality, variability, size, expr, start, v.start is not None,
                           v.unit, v.description, tuple(v.depends) if v.depends is not None else None,
                           tuple(v.items or ()), capacity, v.clock))
        inputs = {v.name for v in out if v.causality == "input"}
        for i, v in enumerate(out):
            if v.depends is not None:
                if v.causality != "output":
                    self.report(("variables", i, "depends"), "only outputs declare depends")
                for name in v.depends:
                    if name not in inputs:
                        self.report(("variables", i, "depends"), f"{name!r} is not an input")
        if not out:
            self.report(("variables",), "an FMU needs at least one variable")
        return tuple(out)

    @staticmethod
    def _default_variability(v: VarCfg) -> str:
        if v.causality == "parameter":
            return "fixed"
        return "continuous" if v.type in FLOATS and v.clock is None else "discrete"

    def _check_type(self, v: VarCfg, size: int | None, path: tuple) -> None:
        """What only some types have: FMI versions, items, capacity, vectors."""
        if v.type in FMI3_ONLY and 2 in self.cfg.fmi:
            self.report((*path, "type"), f"FMI 2.0 has no {v.type} variables: build this FMU for FMI 3.0 only "
                        "(fmi: [3])")
        elif v.type not in FMI1_TYPES and 1 in self.cfg.fmi:  # (FMI 1.0 enumerations need types: not written)
            self.report((*path, "type"), f"an FMI 1.0 build takes {', '.join(FMI1_TYPES)} variables, not {v.type}")
        if v.type == "enumeration":
            items = v.items or []
            if not items or len(set(items)) != len(items):
                self.report((*path, "items"), "an enumeration lists its items, each once")
        elif v.items is not None:
            self.report((*path, "items"), "only an enumeration has items")
        if v.type in TEXT:
            if size is not None:
                self.report((*path, "size"), f"a {v.type} variable is a single value (no size)")
            if v.capacity is not None and not 1 <= v.capacity <= 65536:
                self.report((*path, "capacity"), "capacity is 1 to 65536 bytes")
        elif v.capacity is not None:
            self.report((*path, "capacity"), "only string and binary variables have a capacity")

    def _check_variability(self, v: VarCfg, variability: str, path: tuple) -> None:
        allowed = {"parameter": ("fixed", "tunable"), "input": ("continuous", "discrete"),
                   "output": ("continuous", "discrete"), "local": ("fixed", "tunable", "continuous", "discrete")}
        if variability not in allowed[v.causality]:
            self.report((*path, "variability"), f"a {v.causality} is {' or '.join(allowed[v.causality])}, "
                        f"not {variability}")
        if variability == "continuous" and v.type not in FLOATS:
            self.report((*path, "variability"), f"a {v.type} variable cannot be continuous (use discrete)")
        if v.unit is not None and v.type not in FLOATS:
            self.report((*path, "unit"), "only real and float32 variables carry a unit")

    def _start(self, v: VarCfg, size: int | None, path: tuple) -> tuple[float | int | bool | str | bytes, ...]:
        count = 1 if size is None else size
        if v.type in TEXT:
            return (self._text_start(v, path),)
        default = {"boolean": False, "enumeration": 1}.get(v.type, 0)
        raw = v.start if v.start is not None else default
        values = list(raw) if isinstance(raw, list) else [raw] * count
        if len(values) != count:
            self.report((*path, "start"), f"start has {len(values)} values for a size of {count}")
            return tuple([default] * count)
        out: list[float | int | bool | str | bytes] = []
        for value in values:
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            if v.type == "enumeration" and isinstance(value, str) and value in (v.items or []):
                value = (v.items or []).index(value) + 1
            if v.type == "boolean":
                ok = isinstance(value, bool)
            elif v.type == "enumeration":
                ok = isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= len(v.items or [])
            elif v.type in INT_RANGES:
                low, high = INT_RANGES[v.type]
                ok = isinstance(value, int) and not isinstance(value, bool) and low <= value <= high
            else:
                ok = number and math.isfinite(value) and (v.type == "real" or abs(value) <= 3.4028234663852886e38)
            if not ok:
                what = "item of the enumeration" if v.type == "enumeration" else v.type
                self.report((*path, "start"), f"start value {value!r} is not a finite {what}")
                return tuple([default] * count)
            out.append(float(value) if v.type in FLOATS else value)
        return tuple(out)

    def _text_start(self, v: VarCfg, path: tuple) -> str | bytes:
        raw = "" if v.start is None else v.start
        capacity = v.capacity or DEFAULT_CAPACITY
        if not isinstance(raw, str):
            self.report((*path, "start"), f"the start of a {v.type} variable is " +
                        ("text" if v.type == "string" else "its bytes in hex (\"666f6f\")"))
            return "" if v.type == "string" else b""
        if v.type == "string":
            if len(raw.encode()) >= capacity or "\0" in raw:
                self.report((*path, "start"), f"the start text needs more than the capacity of {capacity} bytes "
                            "(one is for the end)" if "\0" not in raw else "the start text holds a NUL character")
            return raw
        try:
            data = bytes.fromhex(raw)
        except ValueError:
            self.report((*path, "start"), f"{raw!r} is not bytes in hex (\"666f6f\")")
            return b""
        if len(data) > capacity:
            self.report((*path, "start"), f"{len(data)} bytes do not fit the capacity of {capacity}")
        return data

    def _c_state(self, names: set[str]) -> tuple[tuple[str, str, str | None], ...]:
        out = []
        for i, c in enumerate(self.cfg.c_state):
            path = ("c_state", i)
            if not IDENT.match(c.name) or c.name in names or c.name in RESERVED:
                self.report((*path, "name"), f"c_state name {c.name!r} must be a new C identifier")
            if c.ctype not in CTYPES:
                self.report((*path, "ctype"), f"ctype {c.ctype!r} is not one of {', '.join(CTYPES)} "
                            "(the state is copied as plain bytes: no pointers)")
            self._size(c.size, (*path, "size"))
            out.append((c.name, c.ctype, None if c.size is None else str(c.size)))
            names.add(c.name)
        return tuple(out)

    def _sources(self) -> tuple[Path, ...]:
        if self.cfg.sources is None:
            found = sorted(self.folder.glob("*.c"))
            if not found:
                self.report(("sources",), f"no C file in {self.folder}")
            return tuple(found)
        out = []
        for i, name in enumerate(self.cfg.sources):
            path = self.folder / name
            if not path.is_file():
                self.report(("sources", i), f"source file {name!r} not found in {self.folder}")
            out.append(path)
        return tuple(out)


def spec_digest_inputs(spec: FmuSpec) -> list[Path]:
    """Every file a build of ``spec`` reads from its folder (for the content hash)."""
    headers = sorted(spec.folder.glob("*.h"))
    return [spec.folder / SPEC_FILE, *spec.sources, *headers]
