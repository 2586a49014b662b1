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
CTYPES = ("double", "float", "int32_t", "uint32_t", "int64_t", "uint64_t", "uint8_t", "int")
SPEC_FILE = "fmu.yaml"
RESERVED = {"time", "m", "h"}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class VarCfg(_Strict):
    name: str
    type: Literal["real", "integer", "boolean"] = "real"
    causality: Literal["input", "output", "parameter", "local"]
    variability: Literal["fixed", "tunable", "discrete", "continuous"] | None = None
    """Default: ``fixed`` for a parameter, ``continuous`` for a real, ``discrete`` otherwise."""
    size: int | str | None = None
    """A vector of this many values (a number or a name from ``defines``)."""
    start: float | int | bool | list[float | int | bool] | None = None
    unit: str | None = None
    description: str = ""
    depends: list[str] | None = None
    """For an output: the inputs it depends on directly (default: all of them)."""


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
    fmi: list[Literal[2, 3]] = [2]
    defines: dict[str, int] = {}
    sources: list[str] | None = None
    """C files of the model (default: every ``*.c`` in the folder)."""
    cflags: list[str] = []
    step: float | None = None
    """The default communication step in seconds (DefaultExperiment)."""
    capabilities: CapsCfg = CapsCfg()
    variables: list[VarCfg]
    c_state: list[CStateCfg] = []


@dataclass(frozen=True)
class Var:
    """One variable, checked: ``size`` is None for a scalar, ``start`` has one value per element."""

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
            self.report(("fmi",), "fmi lists each version (2, 3) once")
        variables = self._variables()
        c_state = self._c_state({v.name for v in variables})
        sources = self._sources()
        if cfg.step is not None and not (cfg.step > 0 and math.isfinite(cfg.step)):
            self.report(("step",), "step must be a positive number of seconds")
        if cfg.capabilities.serialize and not cfg.capabilities.get_set_state:
            self.report(("capabilities",), "serialize needs get_set_state")
        if self.problems:
            raise _fail(self.problems)
        return FmuSpec(self.folder, cfg.name, cfg.description, cfg.version, tuple(cfg.fmi), dict(cfg.defines),
                       sources, tuple(cfg.cflags), cfg.step, cfg.capabilities.get_set_state,
                       cfg.capabilities.serialize, variables, c_state)

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
            start = self._start(v, size, path)
            out.append(Var(v.name, v.type, v.causality, variability, size, expr, start, v.start is not None,
                           v.unit, v.description, tuple(v.depends) if v.depends is not None else None))
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
        return "continuous" if v.type == "real" else "discrete"

    def _check_variability(self, v: VarCfg, variability: str, path: tuple) -> None:
        allowed = {"parameter": ("fixed", "tunable"), "input": ("continuous", "discrete"),
                   "output": ("continuous", "discrete"), "local": ("fixed", "tunable", "continuous", "discrete")}
        if variability not in allowed[v.causality]:
            self.report((*path, "variability"), f"a {v.causality} is {' or '.join(allowed[v.causality])}, "
                        f"not {variability}")
        if variability == "continuous" and v.type != "real":
            self.report((*path, "variability"), f"a {v.type} variable cannot be continuous (use discrete)")
        if v.unit is not None and v.type != "real":
            self.report((*path, "unit"), "only real variables carry a unit")

    def _start(self, v: VarCfg, size: int | None, path: tuple) -> tuple[float | int | bool, ...]:
        count = 1 if size is None else size
        raw = v.start if v.start is not None else (False if v.type == "boolean" else 0)
        values = list(raw) if isinstance(raw, list) else [raw] * count
        if len(values) != count:
            self.report((*path, "start"), f"start has {len(values)} values for a size of {count}")
            return tuple([0] * count)
        out: list[float | int | bool] = []
        for value in values:
            if v.type == "boolean":
                ok = isinstance(value, bool)
            elif v.type == "integer":
                ok = isinstance(value, int) and not isinstance(value, bool) and -2**31 <= value < 2**31
            else:
                ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            if not ok:
                self.report((*path, "start"), f"start value {value!r} is not a finite {v.type}")
                return tuple([0] * count)
            out.append(float(value) if v.type == "real" else value)
        return tuple(out)

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
