"""Reading an SSP into a scenario (`ssp.read_ssp`; the module docstring of `ssp` says what is read and
how): the archive and its XML, FMPy's reading of it, systems made flat, parameter bindings and mappings,
the chains of connections (`ssp_wiring`) and the experiment."""

from __future__ import annotations

import copy
import os
import posixpath
import re
import shutil
import zipfile
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import unquote, urlsplit

from ..kernel.errors import DynabrainError
from ..kernel.units import NS_PER_S, parse_duration_ns, same_unit
from .ssp import FMU_TYPE, NS, SSD, SSV_TYPE, SSPError, SspImport, _annotation, _ns_text
from .ssp_wiring import Chain, Edge, Node, backward_edges, chains, signal

_DEFAULT_STEP_NS = 2_000_000  # the scenario's own default (world.step: 2ms)
_DEFAULT_DURATION_NS = NS_PER_S


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


class Reader:
    """Reads one SSP (see the module docstring)."""

    def __init__(self, ssp: Path, fmu_dir: Path, scenario_dir: Path, loops: str = "delay"):
        self.ssp, self.fmu_dir, self.scenario_dir, self.loop_mode = ssp, fmu_dir, scenario_dir, loops
        self.label = str(ssp)
        self.problems: list[str] = []
        self.notes: list[str] = []
        self.fmus: list[Path] = []
        self.connectors: dict[tuple[str, ...], dict[str, str]] = {}  # each system's own connectors -> kind
        self.locals: dict[tuple[str, ...], dict[str, tuple[str, Any]]] = {}  # each system's elements
        self.values: dict[Node, Any] = {}  # values bound to systems' own connectors
        self.maps: list[dict[str, Any]] = []  # modules made for linear transformations on connections
        self.loops: list[dict[str, Any]] = []  # `iterate:` entries (loops="iterate")

    def fail(self, message: str) -> None:
        self.problems.append(f"{self.label}: {message}")

    def read(self) -> SspImport:
        names, root = self._open()
        ssd = self._read_ssd(root)
        system, xml_system = ssd.system, root.find("ssd:System", NS)
        components: dict[str, _Component] = {}
        edges: list[Edge] = []
        self._system(system, xml_system, (), components, edges, names)
        connect, events = self._wire(edges, components)
        connect = self._break_loops(connect, components)
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
        scenario.update({"world": world, "modules": [*modules, *self.maps], "connect": connect})
        if self.loops:
            scenario["iterate"] = self.loops
        if events:
            scenario["events"] = events
        return SspImport(scenario, None, tuple(self.fmus), tuple(self.notes))

    # -- systems, nested ones made flat
    def _system(self, system: Any, xml: Any, path: tuple[str, ...], components: dict[str, _Component],
                edges: list[Edge], names: set[str]) -> None:
        """Read ``system`` (at ``path``; the whole one at ``()``): its components (a nested system's named
        ``system_component``), its bindings and its connections (as `Edge` s between connectors)."""
        where = f"system {'.'.join(path) or system.name!r}" if path else f"system {system.name!r}"
        if system.signalDictionaries:
            self.fail(f"{where}: signal dictionaries ({', '.join(repr(d.name) for d in system.signalDictionaries)}) "
                      "are not supported")
        self.connectors[path] = {c.name: c.kind for c in system.connectors}
        local: dict[str, tuple[str, Any]] = {}
        self.locals[path] = local
        xml_elements = {e.get("name"): e for e in xml.iterfind("ssd:Elements/*", NS)}
        for element in system.elements:
            kind = type(element).__name__
            if element.name in local:
                self.fail(f"{where}: two elements are named {element.name!r}")
            elif kind == "System":
                local[element.name] = ("s", (*path, element.name))
                self._system(element, xml_elements[element.name], (*path, element.name), components, edges, names)
            elif kind != "Component":
                self.fail(f"{where}: element {element.name!r} is a {kind}; dynabrain imports systems of FMU components")
            else:
                flat = "_".join((*path, element.name))
                comp = self._component(element, xml_elements[element.name], names, flat)
                if comp is not None and flat in components:
                    self.fail(f"{where}: component {element.name!r} would be module {flat!r}, which is taken")
                elif comp is not None:
                    components[flat] = comp
                    local[element.name] = ("c", flat)
        for name, (kind, flat) in local.items():
            if kind == "c":
                self._bindings(_element_bindings(system, name), components[flat], path, components,
                               xml_elements[name].findall("ssd:ParameterBindings/ssd:ParameterBinding", NS))
        self._bindings(system.parameterBindings, None, path, components,
                       xml.findall("ssd:ParameterBindings/ssd:ParameterBinding", NS))
        xml_connections = list(xml.iterfind("ssd:Connections/ssd:Connection", NS))
        for i, (conn, cx) in enumerate(zip(system.connections, xml_connections, strict=True), 1):
            ends = [(conn.startElement, conn.startConnector), (conn.endElement, conn.endConnector)]
            label = (f"{where}: connection {i} (" + " -> ".join(f"{e or system.name}.{c}" for e, c in ends) + ")")
            found = [self._node(path, components, element, connector, label) for element, connector in ends]
            if None not in found:
                edges.append(Edge(found[0], found[1], cx, label))  # type: ignore[arg-type]

    def _node(self, path: tuple[str, ...], components: dict[str, _Component], element: str | None,
              connector: str, label: str) -> Node | None:
        """The connector ``element.connector`` of the system at ``path`` (its own when ``element`` is empty)."""
        if not element:
            return self._system_connector(path, connector, label)
        ref = self.locals[path].get(element)
        if ref is None:
            if not any(f"component {element!r}" in p for p in self.problems):
                known = ", ".join(self.locals[path]) or "none"
                self.fail(f"{label}: no element {element!r} (elements: {known})")
            return None
        if ref[0] == "s":
            return self._system_connector(ref[1], connector, label)
        comp = components[ref[1]]
        if connector not in comp.connectors:
            known = ", ".join(comp.connectors) or "none"
            self.fail(f"{label}: component {element!r} has no connector {connector!r} (its connectors: {known})")
            return None
        return ("c", (ref[1],), connector) if connector in comp.variables else None

    def _system_connector(self, path: tuple[str, ...], connector: str, label: str) -> Node | None:
        if connector not in self.connectors[path]:
            known = ", ".join(self.connectors[path]) or "none"
            self.fail(f"{label}: system {'.'.join(path) or 'the system'!r} has no connector {connector!r} "
                      f"(its connectors: {known})")
            return None
        return ("j", path, connector)

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
            if major != "1" or "Failed to validate" not in str(exc):
                raise SSPError([f"{self.label}: {exc}"]) from None
            # other tools write what the SSP 1.0 schema does not allow (an .ssv of version 2.0, OMSimulator's
            # own attributes): read it as it is, what the schema says kept in the notes
            said = " ".join(str(exc).split())
            self.notes.append(f"{SSD} does not validate against the SSP 1.0 schema, read as it is: {said[:300]}")
        try:
            return read_ssd(str(self.ssp), validate=False)
        except Exception as exc:
            raise SSPError([f"{self.label}: {exc}"]) from None

    # -- components
    def _component(self, element: Any, xml: Any, names: set[str], flat: str) -> _Component | None:
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
        entry: dict[str, Any] = {"name": flat, "fmu": _relative(path, self.scenario_dir)}
        entry.update(_module_annotation(xml, self.label))
        return _Component(flat, info, variables, connectors, {}, entry)

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
    def _bindings(self, bindings: list[Any], comp: _Component | None, path: tuple[str, ...],
                  components: dict[str, _Component], xml: list[Any]) -> None:
        """Apply ``bindings`` of ``comp`` (or of the system at ``path`` when None: names are
        ``component.variable``, ``system.component.variable`` or the system's own connectors) in order, a
        later value replacing an earlier one."""
        owner = f"component {comp.name!r}" if comp is not None else f"system {'.'.join(path) or 'the system'!r}"
        for binding, xml_binding in zip(bindings, [*xml, *[None] * len(bindings)], strict=False):
            label = f"{owner}: parameter binding {binding.source or '(inline)'}"
            if (binding.type or SSV_TYPE) != SSV_TYPE:
                self.fail(f"{label}: type {binding.type!r} is not an SSV parameter set ({SSV_TYPE})")
                continue
            if binding.sourceBase == "component":
                self.fail(f"{label}: sourceBase 'component' (a file inside the FMU) is not supported")
                continue
            mapping = self._mapping(binding.parameterMapping or (), label, xml_binding)
            for pset in binding.parameterValues:
                for p, name in ((q, t) for src in pset.parameters for q, t in self._mapped(src, mapping, label)):
                    name = (binding.prefix or "") + name
                    target, rest = (comp, name) if comp is not None else self._resolve(path, name, components)
                    if isinstance(target, tuple):  # a system's own connector: its value drives what it is joined to
                        value = self._plain(p, f"{label}: parameter {name!r}")
                        if value is not None:
                            self.values[target] = value
                        continue
                    if target is None or rest not in target.variables:
                        self.notes.append(f"{label}: parameter {name!r} matches no variable and is ignored (as SSP "
                                          "says)")
                        continue
                    self._param(target, rest, p, f"{label}: parameter {name!r}")

    def _mapping(self, mappings: Any, label: str, xml: Any) -> dict[str, list[tuple[str, Any]]]:
        """A binding's parameter mapping (an ``.ssm`` file, or inline: FMPy reads only the file's, so the
        inline one is read here): source name -> [(target name, transformation)]."""
        out: dict[str, list[tuple[str, Any]]] = {}
        entries = [e for mapping in mappings for e in mapping.mappingEntries]
        if xml is not None and not entries:
            entries = [_InlineEntry(e) for e in xml.iterfind("ssd:ParameterMapping/ssm:ParameterMapping/"
                                                              "ssm:MappingEntry", NS)]
        for entry in entries:
            t = entry.transformation
            kind = type(t).__name__ if not hasattr(t, "tag") else _local_name(t)
            if t is not None and not isinstance(t, _Linear) and kind != "LinearTransformation":
                self.fail(f"{label}: mapping {entry.source!r} -> {entry.target!r}: a {kind} (dynabrain maps values "
                          "as they are or through a linear transformation)")
                continue
            out.setdefault(entry.source, []).append((entry.target, t))
        return out

    def _mapped(self, p: Any, mapping: dict[str, list[tuple[str, Any]]], label: str) -> list[tuple[Any, str]]:
        """The parameter ``p`` under its target names (itself when the mapping does not name it), a linear
        transformation applied to its value."""
        if p.name not in mapping:
            return [(p, p.name)]
        out = []
        for target, t in mapping[p.name]:
            q = p
            if t is not None:
                try:
                    value = float(p.value) * float(t.factor or 1) + float(t.offset or 0)
                except (TypeError, ValueError):
                    self.fail(f"{label}: mapping {p.name!r} -> {target!r}: {p.value!r} is not a number to transform")
                    continue
                q = copy.copy(p)
                q.value = repr(value)
            out.append((q, target))
        return out

    def _resolve(self, path: tuple[str, ...], name: str,
                 components: dict[str, _Component]) -> tuple[_Component | Node | None, str]:
        """What ``name`` in a binding of the system at ``path`` names: (a component, its variable), (a
        system's own connector, ""), or (None, name)."""
        head, dot, rest = name.partition(".")
        ref = self.locals.get(path, {}).get(head) if dot else None
        if ref is not None and ref[0] == "c":
            return components[ref[1]], rest
        if ref is not None:
            return self._resolve(ref[1], rest, components)
        if name in self.connectors.get(path, {}):
            return ("j", path, name), ""
        return None, name

    def _plain(self, p: Any, label: str) -> Any:
        """A parameter value as plain data (for a system's own connector: no FMU variable to check it against)."""
        try:
            if p.type == "Real":
                return float(p.value)
            if p.type == "Integer":
                return int(p.value)
            if p.type == "Boolean":
                return str(p.value).strip() in ("true", "1")
        except (TypeError, ValueError):
            self.fail(f"{label}: {p.value!r} is not a {p.type}")
            return None
        self.fail(f"{label}: a {p.type} value for a system's own connector is not supported")
        return None

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
    def _wire(self, edges: list[Edge], components: dict[str, _Component]) -> tuple[list[list[Any]], list[dict]]:
        """The scenario's connections (and t=0 events) of the SSP's chains of connections (`ssp_wiring`)."""
        connect: list[list[Any]] = []
        events: list[dict[str, Any]] = []
        for chain in chains(edges):
            label = chain.edges[0].label
            sig = {n: components[n[1][0]].variables[n[2]][0] for n in chain.components}
            sources = [n for n in chain.components if sig[n].kind == "output"]
            sinks = [n for n in chain.components if sig[n].kind in ("input", "parameter")]
            if len(sources) > 1:
                self.fail(f"{label}: {' and '.join(signal(n) for n in sources)} both drive one chain of connections")
                continue
            if sources:
                for sink in sinks:
                    if sig[sink].kind == "parameter":
                        self.fail(f"{label}: the output {signal(sources[0])} drives the parameter {signal(sink)}")
                    else:
                        scalar = components[sources[0][1][0]].variables[sources[0][2]][1] is not None
                        connect += self._link(chain, sources[0], sink, sig, scalar or sig[sources[0]].shape == ())
                for outer in chain.outer:
                    self.notes.append(f"the system's output {outer[2]!r} is {signal(sources[0])}")
                continue
            value = next((self.values[n] for e in chain.edges for n in (e.a, e.b) if n in self.values), None)
            by = ", ".join(repr(n[2]) for n in chain.outer) or "a nested system's connector"
            for sink in sinks:
                if value is None:
                    self.notes.append(f"{signal(sink)} is the system's input {by}: nothing gives it a value here (set "
                                      "it with an event or from a brain)")
                elif sig[sink].kind == "parameter":
                    components[sink[1][0]].params[sig[sink].name] = value
                else:
                    events.append({"at": "0s", "set": {signal(sink): value}})
                    self.notes.append(f"{signal(sink)} takes {value!r} from the system's {by} (an event at t=0)")
        return connect, events

    def _link(self, chain: Chain, src: Node, dst: Node, sig: dict[Node, Any], scalar: bool) -> list[list[Any]]:
        """The connections that carry ``src`` to ``dst``: one, or two through a module that applies the
        chain's linear transformation (`modules.basic.Gain` with an offset)."""
        a, b = signal(src), signal(dst)
        label = chain.edges[0].label
        transforms = [(e, c) for e in chain.edges for c in e.xml if "Transformation" in str(c.tag)]
        delay = any(_annotation(e.xml, "Connection", self.label).get("delay") == "true" for e in chain.edges)
        if not same_unit(sig[src].unit, sig[dst].unit):
            self.fail(f"{label}: from {sig[src].unit!r} to {sig[dst].unit!r}, a unit conversion, which dynabrain "
                      "does not do")
            return []
        if not transforms:
            return [[a, b, {"delay": True}] if delay else [a, b]]
        edge, t = transforms[0]
        if _local_name(t) != "LinearTransformation" or len(transforms) > 1 or not scalar or \
                (edge.a, edge.b) not in ((src, dst), (dst, src)):
            self.fail(f"{edge.label}: a {_local_name(t)} (dynabrain applies a linear transformation on a connection "
                      "between two components' scalars)")
            return []
        try:
            factor, offset = float(t.get("factor", "1")), float(t.get("offset", "0"))
        except ValueError:
            self.fail(f"{edge.label}: LinearTransformation factor={t.get('factor')!r} offset={t.get('offset')!r}")
            return []
        name = re.sub(r"\W", "_", f"{dst[1][0]}_{dst[2]}_map")
        self.maps.append({"name": name, "python": "dynabrain.modules.basic:Gain",
                          "params": {"k": factor, "offset": offset, "n": 0, "unit": sig[src].unit or "1"}})
        self.notes.append(f"{a} -> {b}: its LinearTransformation (factor {factor:g}, offset {offset:g}) is module "
                          f"{name!r}")
        first = [a, f"{name}.u", {"delay": True}] if delay else [a, f"{name}.u"]
        return [first, [f"{name}.y", b]]

    def _break_loops(self, connect: list[list[Any]], components: dict[str, _Component]) -> list[list[Any]]:
        """Direct connections into feedthrough modules that close a loop (the FMUs declare no dependencies
        that would open it): delayed, the ones that go back in the SSP's order, or with ``loops="iterate"``
        the loop is declared `iterate` instead (strong coupling). Each choice is noted."""
        feedthrough = {n for n, c in components.items() if c.info.feedthrough} | {m["name"] for m in self.maps}
        order = [*components, *(m["name"] for m in self.maps)]
        direct = [(i, c[0].partition(".")[0], c[1].partition(".")[0]) for i, c in enumerate(connect)
                  if len(c) == 2 and c[1].partition(".")[0] in feedthrough]
        back = backward_edges(order, [(s, d) for _, s, d in direct])
        if not back:
            return connect
        if self.loop_mode == "iterate":
            looped = sorted({m for k in back for m in direct[k][1:]}, key=order.index)
            self.loops.append({"name": "ssp_loop", "modules": looped})
            self.notes.append(f"a loop of feedthrough modules ({', '.join(looped)}) is iterated to agreement each "
                              "step (iterate:), as asked")
            return connect
        out = [list(c) for c in connect]
        for k in sorted(back):
            i = direct[k][0]
            out[i] = [*out[i], {"delay": True}]
            self.notes.append(f"{out[i][0]} -> {out[i][1]} is delayed to break a loop of feedthrough modules (their "
                              "FMUs declare no dependencies that would open it); import with loops='iterate' to "
                              "iterate the loop instead")
        return out

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
            if annotation.get("type") == "com.opensimulationplatform":  # libcosim's (OSP)
                algorithm = next(annotation.iter("{*}FixedStepAlgorithm"), None)
                if algorithm is not None and algorithm.get("baseStepSize"):
                    return self._step_of(algorithm.get("baseStepSize"), "the OSP FixedStepAlgorithm annotation")
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


class _InlineEntry:
    """An inline ``ssm:MappingEntry`` as FMPy's file reader would give it (source, target, transformation)."""

    def __init__(self, xml: Any):
        self.source, self.target = xml.get("source"), xml.get("target")
        t = xml.find("ssc:LinearTransformation", NS)
        other = next((c for c in xml if "Transformation" in str(c.tag)), None)
        self.transformation = _Linear(t) if t is not None else other


class _Linear:
    """An inline ``ssc:LinearTransformation`` (its factor and offset as written)."""

    def __init__(self, xml: Any):
        self.factor, self.offset = xml.get("factor"), xml.get("offset")


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
