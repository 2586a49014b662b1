"""Read and check an FMU's model description; map its variables onto ports and parameters.

Inputs and outputs become ports, parameters become module parameters (tunable ones can change at
run time). A vector (an FMI 3.0 array, or FMI 2.0 scalars named ``u[1]``..``u[n]``) is one block
port ``u`` of shape (n,) with a view port per element (``u[1]``...), so it connects as a whole or
element by element. Ports of type real come first, then the other kinds (`BUS_KINDS` order): the
adapter sets and gets each kind with one call.

On the bus (float64): every number type and booleans (FMI 2.0: Real, Integer, Enumeration, Boolean;
FMI 3.0: Float64, Float32, Int8 to UInt64, Boolean, Enumeration). Each converts to float64 exactly,
but 64-bit integers beyond 2^53: a variable that declares such a start, minimum or maximum is refused
here, and a value beyond it at run time fails its step (`session`). Strings, binaries and clocks are
not on the bus: as parameters they are set at load (and at run time when tunable), as inputs and
outputs they are listed in `FmuInfo.skipped`.
"""

from __future__ import annotations

import dataclasses
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .archive import not_regular, open_checked
from .clocks import CLOCK_UNIT, FmuClock, read_clocks
from .errors import FMUError
from .paths import SHARED_LIB_EXT, binary_dir

_TYPES2 = {"Real": "real", "Integer": "integer", "Enumeration": "integer", "Boolean": "boolean", "String": "string"}
_TYPES3 = {"Float64": "real", "Float32": "float32", "Int8": "int8", "UInt8": "uint8", "Int16": "int16",
           "UInt16": "uint16", "Int32": "integer", "UInt32": "uint32", "Int64": "int64", "UInt64": "uint64",
           "Boolean": "boolean", "Enumeration": "int64", "String": "string", "Binary": "binary"}
BUS_KINDS = ("real", "float32", "int8", "uint8", "int16", "uint16", "integer", "uint32", "int64", "uint64", "boolean")
"""The kinds of variables on the bus, in the order a module's ports are laid out."""
INT_RANGES = {"int8": (-2**7, 2**7 - 1), "uint8": (0, 2**8 - 1), "int16": (-2**15, 2**15 - 1),
              "uint16": (0, 2**16 - 1), "integer": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
              "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1)}
EXACT = 2**53
"""Integers up to this size are exact in float64 (the bus)."""
_KIND = {"input": "input", "output": "output", "parameter": "parameter"}
_ORDER = {kind: i for i, kind in enumerate(BUS_KINDS)}
_ELEMENT = re.compile(r"^(.+)\[(\d+)\]$")
DIMENSIONS = {"s": "time", "Hz": "frequency", "kg": "mass", "m": "length", "rad": "angle", "N": "force",
              "N*m": "torque", "m/s": "velocity", "rad/s": "angular_velocity", "m/s^2": "acceleration",
              "rad/s^2": "angular_acceleration"}


@dataclass(frozen=True)
class Signal:
    """A port or parameter made of one or more FMI variables (in value-reference order)."""

    name: str
    kind: str
    """``input``, ``output`` or ``parameter``."""
    type: str
    """``real`` (float64), ``integer`` (int32), ``boolean``, ``float32``, ``int8`` ... ``uint64`` (`BUS_KINDS`),
    ``string`` or ``binary``."""
    vrs: tuple[int, ...]
    shape: tuple[int, ...]
    unit: str
    start: tuple[Any, ...]
    tunable: bool
    description: str
    depends: tuple[int, ...] | None = None
    """For an output: value references of the inputs it depends on directly (None: all)."""
    fmi_type: str = ""
    """The FMI type as the model description writes it (``Enumeration``, ``Int64``, ...)."""
    clocks: tuple[int, ...] = ()
    """FMI 3.0: the value references of the clocks this variable belongs to (a clocked variable: set
    and read in event mode at their ticks); a clock port (type ``clock``) has its own."""

    @property
    def size(self) -> int:
        n = 1
        for d in self.shape:
            n *= d
        return n


@dataclass(frozen=True)
class FmuInfo:
    """What the adapter knows about an FMU before loading its binary."""

    path: str
    version: int
    model_name: str
    model_identifier: str
    token: str
    description: str
    can_get_set: bool
    can_serialize: bool
    once_per_process: bool
    inputs: tuple[Signal, ...]
    outputs: tuple[Signal, ...]
    params: tuple[Signal, ...]
    skipped: tuple[str, ...]
    """Variables the adapter does not expose, each with the reason."""
    default_step: float | None
    source: str = ""
    """What the user named (a source folder, a file); the path when empty."""
    start_time: float = 0.0
    """``DefaultExperiment.startTime``: the FMU's time when it joins a world at t=0 (0 when not given)."""
    clocks: tuple[FmuClock, ...] = ()
    """FMI 3.0 clocks (see `clocks`): the FMU then runs with event mode."""
    scheduled: bool = False
    """FMI 3.0 scheduled execution (an FMU without co-simulation): no steps; the master activates each
    input clock's model partition at its ticks (`events.Events.activate`)."""

    @property
    def label(self) -> str:
        return f"FMU {self.source or Path(self.path).name} ({self.model_name}, FMI {self.version}.0)"

    @property
    def feedthrough(self) -> bool:
        """Whether some output depends directly on some input (the schedule orders consumers after it)."""
        if not self.inputs:
            return False
        return any(o.depends is None or o.depends for o in self.outputs)


def read_fmu_info(path: str | Path, label: str | None = None) -> FmuInfo:
    """Check the FMU at ``path`` (a zip with a valid model description, co-simulation, a binary for
    this platform, variables the adapter can drive) and describe it. Raises `FMUError`."""
    path = Path(path)
    name = label or str(path)
    if not path.exists():
        raise FMUError(f"FMU {name}: file not found")
    not_regular(path, f"FMU {name}")  # (a FIFO would hang the zip reader, a device feed it forever)
    if path.is_dir() or not zipfile.is_zipfile(path):
        raise FMUError(f"FMU {name}: not a zip file (an FMU is a zip archive with a modelDescription.xml)")
    with open_checked(path, f"FMU {name}") as zf:  # (a zip bomb is refused before a member is read)
        names = set(zf.namelist())
    if "modelDescription.xml" not in names:
        raise FMUError(f"FMU {name}: the archive has no modelDescription.xml")
    md = _read_description(path, name)
    version = {"1.0": 1, "2.0": 2}.get(md.fmiVersion, 3 if str(md.fmiVersion).startswith("3.") else None)
    if version is None:
        raise FMUError(f"FMU {name}: FMI version {md.fmiVersion} is not supported (dynabrain runs FMI 1.0, 2.0 and "
                       "3.0)")
    cs = md.coSimulation
    scheduled = cs is None and getattr(md, "scheduledExecution", None) is not None
    if scheduled:
        cs = md.scheduledExecution
    if cs is None:
        kinds = [k for k, v in (("model exchange", md.modelExchange),
                                ("scheduled execution", getattr(md, "scheduledExecution", None))) if v is not None]
        raise FMUError(f"FMU {name}: a {' and '.join(kinds) or 'non-co-simulation'} FMU without co-simulation; "
                       "dynabrain runs co-simulation FMUs, FMI 3.0 clocks included (export it for co-simulation)")
    _check_binary(names, version, cs.modelIdentifier, name)
    clocks = read_clocks(path, md, name) if version == 3 else ()
    inputs, outputs, params, skipped = _signals(md, version, name, clocks)
    experiment = md.defaultExperiment
    step = float(experiment.stepSize) if experiment and experiment.stepSize else None
    start = float(experiment.startTime) if experiment and experiment.startTime else 0.0
    return FmuInfo(str(path), version, md.modelName, cs.modelIdentifier, md.guid or "", md.description or "",
                   bool(cs.canGetAndSetFMUstate), bool(cs.canGetAndSetFMUstate and cs.canSerializeFMUstate),
                   bool(cs.canBeInstantiatedOnlyOncePerProcess), inputs, outputs, params, tuple(skipped), step,
                   label or "", start, clocks, scheduled)


def _read_description(path: Path, name: str) -> Any:
    from fmpy.model_description import ValidationError, read_model_description

    try:
        return read_model_description(str(path), validate=True)
    except ValidationError as exc:
        problems = "\n".join(f"  - {p}" for p in exc.problems[:20])
        raise FMUError(f"FMU {name}: modelDescription.xml does not validate:\n{problems}") from None
    except Exception as exc:  # lxml syntax errors, fmpy's plain Exceptions
        raise FMUError(f"FMU {name}: modelDescription.xml cannot be read: {type(exc).__name__}: {exc}") from None


def _check_binary(names: set[str], version: int, identifier: str, name: str) -> None:
    wanted = f"{binary_dir(version)}/{identifier}{SHARED_LIB_EXT}"
    if wanted in names:
        return
    platforms = sorted({n.split("/")[1] for n in names if n.startswith("binaries/") and n.count("/") >= 2})
    have = f"it has binaries for: {', '.join(platforms)}" if platforms else "it has no binaries (source only?)"
    raise FMUError(f"FMU {name}: no binary for this platform ({wanted} is missing); {have}")


def _unit(variable: Any) -> str:
    unit = variable.unit or (variable.declaredType.unit if variable.declaredType is not None else None)
    return unit.replace(".", "*") if unit else "1"


def _start_values(variable: Any, kind: str, count: int) -> tuple[Any, ...]:
    raw = variable.start
    if kind == "string":
        return ("" if raw is None else str(raw),)
    if kind == "binary":
        return (bytes.fromhex(str(raw or "")),)
    if raw is None:
        values: list[Any] = [0] * count
    else:
        values = str(raw).split() if count > 1 else [raw]
    out: list[Any] = []
    for v in values:
        if kind == "boolean":
            out.append(v in ("true", "1", True, 1))
        elif kind in INT_RANGES:
            out.append(int(v) if isinstance(v, int) or str(v).lstrip("+-").isdigit() else int(float(v)))
        else:
            out.append(float(v))
    if len(out) == 1 and count > 1:
        out *= count
    return tuple(out)


def _shape(variable: Any, md: Any, name: str) -> tuple[int, ...]:
    dims = getattr(variable, "dimensions", None) or []
    shape = []
    for d in dims:
        if d.start is not None and str(d.start) != "":
            shape.append(int(d.start))
            continue
        ref = next((v for v in md.modelVariables if v.valueReference == d.valueReference), None)
        if ref is None or ref.start is None:
            raise FMUError(f"FMU {name}: variable {variable.name!r} has a dimension without a size")
        shape.append(int(ref.start))
    return tuple(shape)


def _signals(md: Any, version: int, name: str, clocks: tuple[FmuClock, ...] = ()) -> tuple[tuple[Signal, ...], ...]:
    types = _TYPES3 if version == 3 else _TYPES2  # FMI 1.0 has FMI 2.0's types
    loose: list[tuple[Any, str, tuple[int, ...]]] = []
    skipped, ports = [], 0
    clock_ports = {c.vr for c in clocks if c.on_bus}
    for v in md.modelVariables:
        if v.causality not in _KIND or (v.type == "Clock" and v.valueReference not in clock_ports):
            continue
        if v.type == "Clock":
            loose.append((v, "clock", ()))
            continue
        kind = types.get(v.type)
        on_bus = kind in BUS_KINDS
        if v.causality != "parameter":
            ports += 1
        if kind is None or (v.causality != "parameter" and not on_bus):
            why = "not supported" if kind is None else "not on the bus"
            skipped.append(f"{v.name} ({v.causality}, {v.type}: {why})")
            continue
        shape = _shape(v, md, name) if version == 3 else ()
        if kind in ("int64", "uint64") and v.causality != "parameter":
            _check_exact(v, name)
        loose.append((v, kind, shape))
    if ports and not any(v.causality != "parameter" for v, _, _ in loose) and not clocks:
        raise FMUError(f"FMU {name}: none of its inputs and outputs can be on the bus: {', '.join(skipped)} (the bus "
                       "takes numbers and booleans: FMI 2.0 Real, Integer, Enumeration, Boolean; FMI 3.0 Float64, "
                       "Float32, Int8 to UInt64, Boolean, Enumeration)")
    groups = _group(loose)
    by_vr = {}
    for sig in groups:
        for vr in sig.vrs:
            by_vr[vr] = sig
    outputs = tuple(_with_depends(s, md, by_vr) for s in groups if s.kind == "output")
    order = {**_ORDER, "string": len(_ORDER), "binary": len(_ORDER) + 1, "clock": len(_ORDER) + 2}

    def key(s: Signal) -> tuple[bool, bool, int]:  # unclocked first, then clocked, then clock ports
        return s.type == "clock", bool(s.clocks), order[s.type]

    pick = [tuple(sorted((s for s in groups if s.kind == k), key=key)) for k in ("input", "parameter")]
    outputs = tuple(sorted(outputs, key=key))
    _check_names(pick[0], outputs, pick[1], name)
    return pick[0], outputs, pick[1], skipped


def _check_exact(variable: Any, name: str) -> None:
    """A 64-bit integer on the bus (float64) must stay within 2^53: refuse one that declares more."""
    declared = variable.declaredType
    for what, raw in (("start", variable.start), ("min", variable.min), ("max", variable.max),
                      ("min", getattr(declared, "min", None)), ("max", getattr(declared, "max", None))):
        if raw is None:
            continue
        values = [int(x) for x in str(raw).split()]
        if any(abs(x) > EXACT for x in values):
            raise FMUError(f"FMU {name}: {variable.type} {variable.causality} {variable.name!r} declares {what}="
                           f"{raw}, beyond 2^53: the bus (float64) holds integers exactly only up to 2^53")


def _group(loose: list[tuple[Any, str, tuple[int, ...]]]) -> list[Signal]:
    """FMI 2.0 scalars ``u[1]``..``u[n]`` of one kind become one vector; everything else stands alone."""
    runs: dict[tuple[str, str, str], list[tuple[int, Any]]] = {}
    for v, kind, shape in loose:
        m = _ELEMENT.match(v.name)
        if m and not shape:
            runs.setdefault((m.group(1), v.causality, kind), []).append((int(m.group(2)), v))
    grouped: dict[int, Signal] = {}
    for (base, causality, kind), items in runs.items():
        items.sort(key=lambda x: x[0])
        vs = [v for _, v in items]
        units = {_unit(v) for v in vs}
        tunable = {v.variability == "tunable" for v in vs}
        if [i for i, _ in items] != list(range(1, len(items) + 1)) or len(units) > 1 or len(tunable) > 1:
            continue
        start = tuple(x for v in vs for x in _start_values(v, kind, 1))
        sig = Signal(base, _KIND[causality], kind, tuple(v.valueReference for v in vs), (len(vs),), units.pop(),
                     start, tunable.pop(), vs[0].description or "", fmi_type=vs[0].type)
        for v in vs:
            grouped[id(v)] = sig
    out: list[Signal] = []
    seen: set[int] = set()
    for v, kind, shape in loose:
        sig = grouped.get(id(v))
        if sig is None:
            count = 1
            for d in shape:
                count *= d
            clocked = tuple(c.valueReference for c in (getattr(v, "clocks", None) or ()))
            if kind == "clock":
                sig = Signal(v.name, _KIND[v.causality], kind, (v.valueReference,), (), CLOCK_UNIT, (0.0,), False,
                             v.description or "", fmi_type="Clock", clocks=(v.valueReference,))
            else:
                sig = Signal(v.name, _KIND[v.causality], kind, (v.valueReference,), shape, _unit(v),
                             _start_values(v, kind, count), v.variability == "tunable", v.description or "",
                             fmi_type=v.type, clocks=clocked)
        if id(sig) not in seen:
            seen.add(id(sig))
            out.append(sig)
    return out


def _with_depends(sig: Signal, md: Any, by_vr: dict[int, Signal]) -> Signal:
    """Attach the inputs an output depends on (from ModelStructure; None when not declared)."""
    deps: set[int] | None = set()
    listed = False
    for unknown in md.outputs:
        if unknown.variable.valueReference not in sig.vrs:
            continue
        listed = True
        if unknown.dependencies is None or deps is None:
            deps = None
            continue
        for dep in unknown.dependencies:
            src = by_vr.get(dep.valueReference)
            if src is not None and src.kind == "input":
                deps.add(dep.valueReference)
    if not listed:
        deps = None
    return dataclasses.replace(sig, depends=None if deps is None else tuple(sorted(deps)))


def _check_names(inputs: tuple[Signal, ...], outputs: tuple[Signal, ...], params: tuple[Signal, ...],
                 name: str) -> None:
    seen: dict[str, str] = {}
    for sig in (*inputs, *outputs, *params):
        names = [sig.name] + ([f"{sig.name}[{i + 1}]" for i in range(sig.shape[0])] if len(sig.shape) == 1 else [])
        for n in names:
            if n in seen:
                raise FMUError(f"FMU {name}: the name {n!r} is used by an {seen[n]} and by an {sig.kind}")
            seen[n] = sig.kind
