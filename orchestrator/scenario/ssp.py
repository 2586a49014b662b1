"""SSP in and out: systems of FMUs (System Structure and Parameterization, a Modelica Association
standard) as dynabrain scenarios, and scenarios of FMUs as SSPs.

An SSP is a zip archive with ``SystemStructure.ssd`` at its root and the FMUs (and ``.ssv`` parameter
files) under ``resources/``. `import_ssp` turns one into a scenario: each component a module
(``fmu:`` the FMU extracted beside the scenario), each connection a ``connect`` entry
(``element.connector`` -> ``module.port``: connectors are named like the FMU's variables, and so are
dynabrain's ports), each parameter binding's values (inline or in an ``.ssv`` file, at the component
or at the system with ``component.`` names) the module's ``params``, and the default experiment
``world:`` (``core: null``: a system of FMUs has no physics core). `export_ssp` writes the SSP of a
scenario whose modules all are FMUs.

The structure is read by FMPy's SSP reader (`fmpy.ssp.ssd.read_ssd`, which validates an SSD 1.x
against the SSP 1.0 schema it ships). What that reader leaves out is read here from the same XML, no
more: the default experiment, the step (OMSimulator's ``FixedStepMaster`` annotation, or dynabrain's
own), connector units, transformations on connections and a component's ``implementation``.

What dynabrain cannot run is refused, naming the file and the element: a component that is not an
FMU (a nested SSD or SSP), a nested system, signal dictionaries, parameter mappings, unit conversions
(a connection between different units, a parameter value or a connector in another unit than the
FMU's variable, a transformation on a connection), connections to the system's own connectors,
enumeration values, start values of inputs. Parameter names that match no variable are ignored, as
SSP says, and listed in the import's notes.

Written SSPs are SSD version 1.0 (the namespaces ``http://ssp-standard.org/SSP1/...``, which SSP 2.0
keeps): everything written is in SSP 1.0, SSP 2.0 readers read 1.0 files, and FMPy's reader and
schemas take 1.x only. Each SSD is checked against FMPy's copy of the SSP 1.0 schemas before it is
written. What SSP cannot say and a round trip needs (the step in integer nanoseconds, seed, history,
module periods, ``isolate``, ``delay`` on a connection) goes into annotations of type
``org.dynabrain.scenario``, which other tools ignore. Reading is here, writing in `ssp_export`.
"""

from __future__ import annotations

import os
import posixpath
import shutil
import zipfile
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import unquote, urlsplit

from ..kernel.errors import DynabrainError, Problem
from ..kernel.units import NS_PER_S, parse_duration_ns, same_unit

SSD = "SystemStructure.ssd"
NS = {"ssd": "http://ssp-standard.org/SSP1/SystemStructureDescription",
      "ssc": "http://ssp-standard.org/SSP1/SystemStructureCommon",
      "ssv": "http://ssp-standard.org/SSP1/SystemStructureParameterValues",
      "db": "urn:dynabrain:ssp:1"}
ANNOTATION = "org.dynabrain.scenario"
"""The type of dynabrain's annotations (world, module and connection settings SSP has no words for)."""
FMU_TYPE = "application/x-fmu-sharedlibrary"
SSV_TYPE = "application/x-ssp-parameter-set"
_DEFAULT_STEP_NS = 2_000_000  # the scenario's own default (world.step: 2ms)
_DEFAULT_DURATION_NS = NS_PER_S


class SSPError(DynabrainError):
    """An SSP that cannot be imported, or a scenario that cannot be exported; ``problems`` lists every
    reason, each naming the file and the element (component, connector, connection, parameter)."""

    def __init__(self, problems: list[str] | list[Problem] | list[str | Problem], what: str = "SSP"):
        self.problems = [str(p) for p in problems]
        count = len(self.problems)
        super().__init__(f"{count} problem{'s' if count != 1 else ''} with the {what}:\n"
                         + "\n".join(f"  - {p}" for p in self.problems))


@dataclass(frozen=True)
class SspImport:
    """What `import_ssp` made: the scenario (plain data, as written), where, the FMUs it extracted and
    notes (what was ignored as SSP says, where the step and the duration came from)."""

    scenario: dict[str, Any]
    path: Path | None
    fmus: tuple[Path, ...]
    notes: tuple[str, ...]


@dataclass(frozen=True)
class SspExport:
    """What `export_ssp` wrote: the file, the SSD version, components and connections (SSP's, one per
    connected variable), the FMUs under ``resources/``, what the scenario holds that SSP cannot say,
    and whether the SSD was checked against the SSP schemas."""

    path: Path
    version: str
    components: tuple[str, ...]
    connections: int
    resources: tuple[str, ...]
    left_out: tuple[str, ...]
    validated: bool


# -- reading -------------------------------------------------------------------------------------------
def import_ssp(ssp: str | os.PathLike[str], scenario: str | os.PathLike[str] | None = None, *,
               fmu_dir: str | os.PathLike[str] | None = None, check: bool = True) -> SspImport:
    """Write the scenario of the SSP at ``ssp`` to ``scenario`` (default: beside the SSP, ``.yaml``)
    and extract its FMUs to ``fmu_dir`` (default: a folder named after the scenario, beside it).
    ``check``: build the scenario once (every FMU loaded, every connection checked) and raise if it
    does not validate. Raises `SSPError` naming the file and each element at fault."""
    ssp = Path(ssp)
    out = Path(scenario) if scenario is not None else ssp.with_suffix(".yaml")
    folder = Path(fmu_dir) if fmu_dir is not None else out.with_suffix("")
    result = read_ssp(ssp, folder, scenario_dir=out.parent)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(_yaml(result.scenario, ssp, result.notes))
    result = SspImport(result.scenario, out, result.fmus, result.notes)
    if check:
        from ..kernel.errors import ScenarioError
        from .model import load_world

        try:
            load_world(out).close()
        except ScenarioError as exc:
            raise SSPError([f"{ssp}: the scenario written to {out} does not validate:", *exc.problems]) from None
    return result


def read_ssp(ssp: str | os.PathLike[str], fmu_dir: str | os.PathLike[str], *,
             scenario_dir: str | os.PathLike[str] = ".") -> SspImport:
    """The scenario of the SSP at ``ssp`` as plain data (not written), its FMUs extracted to
    ``fmu_dir`` and named relative to ``scenario_dir``. Raises `SSPError`."""
    return _Reader(Path(ssp), Path(fmu_dir), Path(scenario_dir)).read()


@dataclass
class _Component:
    name: str
    info: Any  # FmuInfo
    variables: dict[str, tuple[Any, int | None]]
    """Connector names (the FMU's variable names on the bus) -> (signal, element index or None)."""
    connectors: dict[str, str]
    """Declared connectors -> kind."""
    params: dict[str, Any]
    entry: dict[str, Any]


class _Reader:
    def __init__(self, ssp: Path, fmu_dir: Path, scenario_dir: Path):
        self.ssp, self.fmu_dir, self.scenario_dir = ssp, fmu_dir, scenario_dir
        self.label = str(ssp)
        self.problems: list[str] = []
        self.notes: list[str] = []
        self.fmus: list[Path] = []

    def fail(self, message: str) -> None:
        self.problems.append(f"{self.label}: {message}")

    def read(self) -> SspImport:
        names, root = self._open()
        ssd = self._read_ssd(root)
        system, xml_system = ssd.system, root.find("ssd:System", NS)
        where = f"system {system.name!r}"
        self._unsupported(system, where)
        components: dict[str, _Component] = {}
        xml_components = {c.get("name"): c for c in xml_system.iterfind("ssd:Elements/ssd:Component", NS)}
        for element in system.elements:
            kind = type(element).__name__
            if kind != "Component":
                self.fail(f"{where}: element {element.name!r} is a {'nested system' if kind == 'System' else kind}; "
                          "dynabrain imports a system of FMU components only")
                continue
            if element.name in components:
                self.fail(f"{where}: two elements are named {element.name!r}")
                continue
            comp = self._component(element, xml_components[element.name], names)
            if comp is not None:
                components[comp.name] = comp
        for comp in components.values():
            self._bindings(_element_bindings(system, comp.name), comp, components, where)
        self._bindings(system.parameterBindings, None, components, where)
        connect = self._connections(system, xml_system, components)
        world = self._world(root, xml_system, components)
        if self.problems:
            raise SSPError(self.problems)
        modules = []
        for comp in components.values():
            if comp.params:
                comp.entry["params"] = comp.params
            modules.append(comp.entry)
        scenario: dict[str, Any] = {"name": root.get("name") or system.name or self.ssp.stem,
                                    "description": f"imported from {self.ssp.name} (SSP, SSD {root.get('version')})"}
        scenario.update({"world": world, "modules": modules, "connect": connect})
        return SspImport(scenario, None, tuple(self.fmus), tuple(self.notes))

    # -- the archive, the XML and FMPy's reading of it
    def _open(self) -> tuple[set[str], Any]:
        from lxml import etree

        if not self.ssp.is_file():
            raise SSPError([f"{self.label}: no such file"])
        if not zipfile.is_zipfile(self.ssp):
            raise SSPError([f"{self.label}: not a zip file (an SSP is a zip archive with {SSD} at its root)"])
        with zipfile.ZipFile(self.ssp) as zf:
            names = set(zf.namelist())
            if SSD not in names:
                some = ", ".join(sorted(names)[:6]) or "nothing"
                raise SSPError([f"{self.label}: the archive has no {SSD} at its root (it holds {some})"])
            data = zf.read(SSD)
            xml_members = [n for n in names if n.endswith((".ssd", ".ssv", ".ssm", ".ssb"))]
            for member in xml_members:  # FMPy parses these with lxml's defaults: no DTD gets that far
                if b"<!DOCTYPE" in zf.read(member)[:4096]:
                    raise SSPError([f"{self.label}: {member} declares a DTD (<!DOCTYPE>); SSP files have none"])
        try:
            root = etree.fromstring(data, etree.XMLParser(resolve_entities=False, no_network=True))
        except etree.XMLSyntaxError as exc:
            raise SSPError([f"{self.label}: {SSD} is not well-formed XML: {exc}"]) from None
        if root.tag != f"{{{NS['ssd']}}}SystemStructureDescription":
            raise SSPError([f"{self.label}: {SSD}: the root element is {root.tag!r}, not SystemStructureDescription "
                            f"in the namespace {NS['ssd']}"])
        if root.find("ssd:System", NS) is None:
            raise SSPError([f"{self.label}: {SSD} has no System element"])
        return names, root

    def _read_ssd(self, root: Any) -> Any:
        from fmpy.ssp.ssd import read_ssd

        version = root.get("version") or ""
        major = version.split(".")[0]
        if major not in ("1", "2"):
            raise SSPError([f"{self.label}: {SSD} version {version!r}: dynabrain reads SSP 1.x and 2.x"])
        if major == "2":
            self.notes.append(f"SSD version {version}: not checked against a schema (FMPy ships SSP 1.0's only)")
        try:
            return read_ssd(str(self.ssp), validate=major == "1")
        except KeyError as exc:  # a file the SSD names is not in the archive
            raise SSPError([f"{self.label}: {SSD} names a file the archive does not hold: {exc.args[0]}"]) from None
        except Exception as exc:  # FMPy raises plain Exceptions (schema), lxml its syntax errors (.ssv)
            raise SSPError([f"{self.label}: {exc}"]) from None

    def _unsupported(self, system: Any, where: str) -> None:
        if system.signalDictionaries:
            names = ", ".join(repr(d.name) for d in system.signalDictionaries)
            self.fail(f"{where}: signal dictionaries ({names}) are not supported")
        if system.connectors:
            self.notes.append(f"{where}: its own connectors ({', '.join(c.name for c in system.connectors)}) "
                              "are an interface to an enclosing system; nothing drives them here")

    # -- components
    def _component(self, element: Any, xml: Any, names: set[str]) -> _Component | None:
        where = f"component {element.name!r}"
        ctype = element.type or FMU_TYPE
        before = len(self.problems)
        if ctype != FMU_TYPE:
            self.fail(f"{where}: type {ctype!r} is not an FMU ({FMU_TYPE}); dynabrain imports FMU components "
                      "(a component that is an SSD or an SSP is a nested system)")
        if xml.get("implementation") == "ModelExchange":
            self.fail(f"{where}: implementation ModelExchange; dynabrain runs co-simulation FMUs")
        if "." in element.name or element.name != element.name.strip():
            self.fail(f"{where}: a module name has no dots and no surrounding spaces (signals are module.port)")
        member = self._member(element.source, where, names)
        if member is None or len(self.problems) > before:
            return None
        path = self._extract(member)
        from ..fmu.errors import FMUError
        from ..fmu.info import read_fmu_info

        try:
            info = read_fmu_info(path, label=member)
        except FMUError as exc:
            self.fail(f"{where}: {exc}")
            return None
        variables = _variables(info)
        skipped = {s.split(" (")[0]: s for s in info.skipped}
        connectors: dict[str, str] = {}
        xml_connectors = {c.get("name"): c for c in xml.iterfind("ssd:Connectors/ssd:Connector", NS)}
        for conn in element.connectors:
            connectors[conn.name] = conn.kind
            self._connector(where, conn, xml_connectors.get(conn.name), variables, skipped, info)
        entry: dict[str, Any] = {"name": element.name, "fmu": _relative(path, self.scenario_dir)}
        entry.update(_module_annotation(xml, self.label))
        return _Component(element.name, info, variables, connectors, {}, entry)

    def _member(self, source: str | None, where: str, names: set[str]) -> str | None:
        if not source:
            self.fail(f"{where}: no source")
            return None
        parts = urlsplit(source)
        path = unquote(parts.path)
        pure = PurePosixPath(path)
        if parts.scheme or parts.netloc or parts.fragment or pure.is_absolute() or ".." in pure.parts:
            self.fail(f"{where}: source {source!r}: dynabrain reads components inside the SSP, named by a relative "
                      "path (resources/NAME.fmu)")
            return None
        member = posixpath.normpath(path)
        if member not in names:
            self.fail(f"{where}: source {source!r} is not in the archive")
            return None
        return member

    def _extract(self, member: str) -> Path:
        dest = self.fmu_dir.joinpath(*PurePosixPath(member).parts)
        if dest not in self.fmus:
            dest.parent.mkdir(parents=True, exist_ok=True)
            with zipfile.ZipFile(self.ssp) as zf, zf.open(member) as src, open(dest, "wb") as out:
                shutil.copyfileobj(src, out)
            self.fmus.append(dest)
        return dest

    def _connector(self, where: str, conn: Any, xml: Any, variables: dict[str, tuple[Any, int | None]],
                   skipped: dict[str, str], info: Any) -> None:
        label = f"{where}: connector {conn.name!r}"
        if conn.name in skipped:
            self.fail(f"{label}: the variable is not on dynabrain's bus: {skipped[conn.name]}")
            return
        if conn.name not in variables:
            known = ", ".join(sorted(variables)) or "none"
            self.fail(f"{label} names no variable of {info.label} (its inputs, outputs and parameters: {known})")
            return
        sig, _ = variables[conn.name]
        if conn.kind in ("calculatedParameter", "inout") or conn.kind != sig.kind:
            self.fail(f"{label}: kind {conn.kind!r}, but the FMU's variable is an {sig.kind}")
        typed = next((c for c in (xml if xml is not None else ()) if c.tag.startswith(f"{{{NS['ssc']}}}")), None)
        unit = typed.get("unit") if typed is not None else None
        if unit and not same_unit(unit, sig.unit):
            self.fail(f"{label} is in {unit!r} and the FMU's variable in {sig.unit!r}: a unit conversion, which "
                      "dynabrain does not do")

    # -- parameters
    def _bindings(self, bindings: list[Any], comp: _Component | None, components: dict[str, _Component],
                  where: str) -> None:
        """Apply ``bindings`` of ``comp`` (or of the system when None: names are ``component.variable``)
        in order, a later value replacing an earlier one."""
        owner = f"component {comp.name!r}" if comp is not None else where
        for binding in bindings:
            label = f"{owner}: parameter binding {binding.source or '(inline)'}"
            if (binding.type or SSV_TYPE) != SSV_TYPE:
                self.fail(f"{label}: type {binding.type!r} is not an SSV parameter set ({SSV_TYPE})")
                continue
            if binding.parameterMapping:
                self.fail(f"{label}: parameter mappings (.ssm) are not supported")
                continue
            if binding.sourceBase == "component":
                self.fail(f"{label}: sourceBase 'component' (a file inside the FMU) is not supported")
                continue
            for pset in binding.parameterValues:
                for p in pset.parameters:
                    name = (binding.prefix or "") + p.name
                    target, rest = comp, name
                    if comp is None:
                        head, _, rest = name.partition(".")
                        target = components.get(head) if rest else None
                    if target is None or rest not in target.variables:
                        self.notes.append(f"{label}: parameter {name!r} matches no variable and is ignored (as SSP "
                                          "says)")
                        continue
                    self._param(target, rest, p, f"{label}: parameter {name!r}")

    def _param(self, comp: _Component, name: str, p: Any, label: str) -> None:
        sig, index = comp.variables[name]
        if sig.kind != "parameter":
            self.fail(f"{label} sets the start value of an {sig.kind}; dynabrain sets parameters only (connect the "
                      "input, or set it with an event)")
            return
        value = self._value(p, sig, label)
        if value is None:
            return
        if index is None:
            comp.params[sig.name] = value
        else:  # one element of an FMI 2.0 vector (k[1]..k[n]): the module's parameter is the vector
            vector = comp.params.setdefault(sig.name, list(sig.start))
            vector[index] = value

    def _value(self, p: Any, sig: Any, label: str) -> Any:
        kinds = {"Real": ("real", "float32"), "Integer": ("real", "float32", "integer", "int8", "uint8", "int16",
                                                          "uint16", "uint32", "int64", "uint64"),
                 "Boolean": ("boolean",), "String": ("string",), "Binary": ("binary",)}
        if p.type not in kinds:
            self.fail(f"{label}: {p.type or 'this type of'} values are not supported")
            return None
        if sig.type not in kinds[p.type]:
            self.fail(f"{label}: a {p.type} value for the FMU's {sig.fmi_type} variable")
            return None
        if p.type == "Real" and p.unit and not same_unit(p.unit, sig.unit):
            self.fail(f"{label} is in {p.unit!r} and the FMU's variable in {sig.unit!r}: a unit conversion, which "
                      "dynabrain does not do")
            return None
        try:
            if p.type == "Real":
                return float(p.value)
            if p.type == "Integer":
                return int(p.value) if sig.type not in ("real", "float32") else float(int(p.value))
        except (TypeError, ValueError):
            self.fail(f"{label}: {p.value!r} is not a {p.type}")
            return None
        if p.type == "Boolean":
            return str(p.value).strip() in ("true", "1")
        return p.value  # a string, or a binary's hex digits (as a scenario writes them)

    # -- connections and the experiment
    def _connections(self, system: Any, xml_system: Any, components: dict[str, _Component]) -> list[list[Any]]:
        out: list[list[Any]] = []
        xml_connections = list(xml_system.iterfind("ssd:Connections/ssd:Connection", NS))
        for i, (conn, xml) in enumerate(zip(system.connections, xml_connections, strict=True), 1):
            ends = [(conn.startElement, conn.startConnector), (conn.endElement, conn.endConnector)]
            label = f"connection {i} ({' -> '.join(f'{e or system.name}.{c}' for e, c in ends)})"
            if conn.startElement is None or conn.endElement is None:
                self.fail(f"{label} uses the system's own connectors (an interface to an enclosing system); "
                          "dynabrain connects components only")
                continue
            found = [self._end(label, element, connector, components) for element, connector in ends]
            if None in found:
                continue
            (a, sig_a), (b, sig_b) = found  # type: ignore[misc]
            if (sig_a.kind, sig_b.kind) == ("input", "output"):
                (a, sig_a), (b, sig_b) = (b, sig_b), (a, sig_a)
            elif (sig_a.kind, sig_b.kind) != ("output", "input"):
                self.fail(f"{label} joins an {sig_a.kind} and an {sig_b.kind}; a connection goes from an output to "
                          "an input")
                continue
            if not same_unit(sig_a.unit, sig_b.unit):
                self.fail(f"{label}: from {sig_a.unit!r} to {sig_b.unit!r}, a unit conversion, which dynabrain does "
                          "not do")
            transform = [c for c in xml if "Transformation" in str(c.tag)]
            if transform:
                self.fail(f"{label}: a {_local_name(transform[0])} (transformations are not supported)")
            entry: list[Any] = [a, b]
            if _annotation(xml, "Connection", self.label).get("delay") == "true":
                entry.append({"delay": True})
            out.append(entry)
        return out

    def _end(self, label: str, element: str, connector: str,
             components: dict[str, _Component]) -> tuple[str, Any] | None:
        comp = components.get(element)
        if comp is None:
            if not any(p.startswith(f"{self.label}: component {element!r}") for p in self.problems):
                self.fail(f"{label}: no FMU component {element!r} (components: {', '.join(components) or 'none'})")
            return None
        if connector not in comp.connectors:
            known = ", ".join(comp.connectors) or "none"
            self.fail(f"{label}: component {element!r} has no connector {connector!r} (its connectors: {known})")
            return None
        if connector not in comp.variables:
            return None  # reported with the component's connectors
        return f"{element}.{connector}", comp.variables[connector][0]

    def _world(self, root: Any, xml_system: Any, components: dict[str, _Component]) -> dict[str, Any]:
        experiment = root.find("ssd:DefaultExperiment", NS)
        mine = _annotation(experiment, "World", self.label) if experiment is not None else {}
        start = self._time(experiment, "startTime") or Fraction(0)
        stop = self._time(experiment, "stopTime")
        world: dict[str, Any] = {"core": None}
        step_ns = self._step(mine, xml_system, components)
        if "duration_ns" in mine:
            duration_ns = mine["duration_ns"]
        elif stop is not None:
            duration = (stop - start) * NS_PER_S
            duration_ns = int(duration)
            if duration.denominator != 1 or duration_ns <= 0:
                self.fail(f"DefaultExperiment: stopTime - startTime ({float(duration) / NS_PER_S:g} s) is not a "
                          "positive whole number of nanoseconds")
        else:
            duration_ns = _DEFAULT_DURATION_NS
            self.notes.append("no DefaultExperiment stopTime: the scenario runs 1 s")
        if step_ns and duration_ns % step_ns:
            self.fail(f"DefaultExperiment: the duration ({_ns_text(duration_ns)}) is not a whole number of "
                      f"{_ns_text(step_ns)} steps")
        starts = {c.info.start_time for c in components.values()}
        if start and starts != {float(start)}:
            self.fail(f"DefaultExperiment: startTime {float(start):g} s; a dynabrain world starts at 0 and each FMU "
                      "at its own DefaultExperiment startTime (here: "
                      + ", ".join(f"{c.name} {c.info.start_time:g} s" for c in components.values()) + ")")
        world.update(step=_ns_text(step_ns), duration=_ns_text(duration_ns))
        for key in ("seed", "history"):
            if key in mine:
                world[key] = mine[key]
        return world

    def _time(self, experiment: Any, key: str) -> Fraction | None:
        text = experiment.get(key) if experiment is not None else None
        if text is None:
            return None
        try:
            return Fraction(text.strip())
        except (ValueError, ZeroDivisionError):
            self.fail(f"DefaultExperiment: {key}={text!r} is not a finite number of seconds")
            return None

    def _step(self, mine: dict[str, str], xml_system: Any, components: dict[str, _Component]) -> int:
        """dynabrain's annotation, else OMSimulator's ``FixedStepMaster``, else the smallest default step
        of the FMUs, else the scenario's default (2 ms)."""
        if "step_ns" in mine:
            return mine["step_ns"]
        for annotation in xml_system.iterfind("ssd:Annotations/ssc:Annotation", NS):
            if annotation.get("type") != "org.openmodelica":
                continue
            master = next(annotation.iter("{*}FixedStepMaster"), None)
            if master is not None and master.get("stepSize"):
                return self._step_of(master.get("stepSize"), "OMSimulator's FixedStepMaster annotation")
        steps = [(c.info.default_step, c.name) for c in components.values() if c.info.default_step]
        if steps:
            step, name = min(steps)
            return self._step_of(repr(step), f"the smallest default step of the FMUs ({name}'s)")
        self.notes.append("step 2ms: the scenario's default (neither the SSP nor its FMUs give one)")
        return _DEFAULT_STEP_NS

    def _step_of(self, text: str, source: str) -> int:
        try:
            ns = parse_duration_ns(text)
            if ns <= 0:
                raise DynabrainError("a step is above 0")
        except DynabrainError as exc:
            self.fail(f"step {text!r} from {source}: {exc}")
            return 0
        self.notes.append(f"step {_ns_text(ns)}: from {source}")
        return ns


def _element_bindings(system: Any, name: str) -> list[Any]:
    """The parameter bindings of the component ``name`` of ``system`` (as FMPy read them)."""
    return next((e.parameterBindings for e in system.elements if e.name == name), [])


def _variables(info: Any) -> dict[str, tuple[Any, int | None]]:
    """The FMU's variables on the bus by their FMI names: an FMI 2.0 vector is its scalars ``u[1]``..,
    an FMI 3.0 array one variable."""
    out: dict[str, tuple[Any, int | None]] = {}
    for sig in (*info.inputs, *info.outputs, *info.params):
        if len(sig.vrs) > 1:
            out.update({f"{sig.name}[{i + 1}]": (sig, i) for i in range(len(sig.vrs))})
        else:
            out[sig.name] = (sig, None)
    return out


_WHOLE = ("step_ns", "duration_ns", "period_ns", "call_timeout_ns", "seed", "history")


def _annotation(xml: Any, what: str, file: str = "") -> dict[str, Any]:
    """The attributes of dynabrain's ``db:<what>`` annotation on ``xml`` (empty when there is none),
    whole numbers as ints. Raises `SSPError` for one that is not a whole number at least 0."""
    for annotation in xml.iterfind("ssd:Annotations/ssc:Annotation", NS):
        if annotation.get("type") != ANNOTATION or annotation.find(f"db:{what}", NS) is None:
            continue
        out: dict[str, Any] = dict(annotation.find(f"db:{what}", NS).attrib)
        for key in set(out) & set(_WHOLE):
            text = out[key]
            out[key] = int(text) if text.isdigit() and (int(text) > 0 or key in ("seed", "history")) else None
            if out[key] is None:
                raise SSPError([f"{file}: annotation {ANNOTATION}, {what}: {key}={text!r} is not a whole number "
                                "(above 0 for a duration)"])
        return out
    return {}


def _module_annotation(xml: Any, file: str) -> dict[str, Any]:
    mine = _annotation(xml, "Module", file)
    out: dict[str, Any] = {}
    if "period_ns" in mine:
        out["period"] = _ns_text(mine["period_ns"])
    if mine.get("isolate") == "true":
        out["isolate"] = True
    if "call_timeout_ns" in mine:
        out["call_timeout"] = _ns_text(mine["call_timeout_ns"])
    return out


def _local_name(element: Any) -> str:
    return str(element.tag).rpartition("}")[2]


def _relative(path: Path, folder: Path) -> str:
    return Path(os.path.relpath(path.resolve(), folder.resolve())).as_posix()


def _ns_text(ns: int) -> str:
    """An exact duration in the largest unit that holds it whole (``2ms``, ``1500us``)."""
    for unit, scale in (("s", NS_PER_S), ("ms", 1_000_000), ("us", 1000)):
        if ns and ns % scale == 0:
            return f"{ns // scale}{unit}"
    return f"{ns}ns"


def _yaml(scenario: dict[str, Any], ssp: Path, notes: tuple[str, ...]) -> str:
    """The scenario as the shipped ones are written: a module or a connection a line."""
    import yaml

    def flow(value: Any) -> str:
        text = yaml.safe_dump(value, default_flow_style=True, width=10**6, allow_unicode=True, sort_keys=False)
        return text.removesuffix("\n...\n").strip()  # (a plain scalar is a document of its own)

    lines = [f"# Imported from {ssp.name} by `dynabrain ssp import`.", *(f"# note: {n}" for n in notes)]
    for key, value in scenario.items():
        if isinstance(value, list):
            lines.append(f"{key}:" + ("" if value else " []"))
            lines += [f"  - {flow(item)}" for item in value]
        else:
            lines.append(f"{key}: {flow(value)}")
    return "\n".join(lines) + "\n"


# -- writing (ssp_export) ---------------------------------------------------------------------------
def export_ssp(scenario: str | os.PathLike[str], ssp: str | os.PathLike[str]) -> SspExport:
    """Write the SSP of the scenario at ``scenario`` (its modules all FMUs, ``world.core: null``) to
    ``ssp``: ``SystemStructure.ssd`` (version 1.0) and the FMUs under ``resources/``. Raises
    `ScenarioError` for a scenario that does not validate, `SSPError` naming each module, connection or
    parameter SSP cannot hold."""
    from .ssp_export import write_ssp

    return write_ssp(scenario, ssp)
