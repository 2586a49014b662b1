"""`export_ssp` (see `ssp`): the SSP of a scenario whose modules all are FMUs. The SSD is built
with lxml, checked against FMPy's copy of the SSP 1.0 schemas (the SSD and each inline parameter set),
and written with the FMUs into a zip that replaces the target only once complete."""

from __future__ import annotations

import os
import tempfile
import zipfile
from pathlib import Path
from typing import Any

from ..kernel.errors import DynabrainError, Problem
from ..kernel.units import NS_PER_S, parse_duration_ns
from .ssp import ANNOTATION, FMU_TYPE, NS, SSD, SSPError, SspExport

_SSC_TYPES = {"real": "Real", "float32": "Real", "boolean": "Boolean"}  # any other number: Integer
_INT32 = (-2**31, 2**31 - 1)


def write_ssp(scenario: str | os.PathLike[str], ssp: str | os.PathLike[str]) -> SspExport:
    """`ssp.export_ssp`: see there."""
    from .model import load_scenario

    sc = load_scenario(scenario)
    refused = []
    if sc.model.world.core is not None:
        refused.append(sc.source.problem(("world", "core"), f"the physics core ({sc.model.world.core}) is not an FMU; "
                                         "an SSP is a system of FMUs (an FMU-only scenario has world: {core: null})"))
    for i, cfg in enumerate(sc.model.modules):
        if cfg.fmu is None:
            refused.append(sc.source.problem(("modules", i, "python"), f"module {cfg.name!r} ({cfg.python}) is a "
                                             "Python module; SSP components are FMUs"))
    if refused:
        raise SSPError(refused, "scenario")
    world = sc.build()
    try:
        return _Writer(sc, world).write(Path(ssp))
    finally:
        world.close()


class _Writer:
    def __init__(self, sc: Any, world: Any):
        from lxml import etree

        self.etree = etree
        self.sc, self.world = sc, world
        self.problems: list[Problem] = []
        self.resources: dict[str, str] = {}  # FMU file -> its name in the archive
        self.connections = 0
        self.enumerations: dict[str, list[tuple[str, int]]] = {}  # enumeration type -> its items (ssd:Enumerations)
        self._descriptions: dict[str, Any] = {}  # FMU file -> its model description (FMPy's), read when needed

    def el(self, parent: Any, tag: str, **attrib: str) -> Any:
        prefix, _, name = tag.partition(":")
        return self.etree.SubElement(parent, f"{{{NS[prefix]}}}{name}", attrib)

    def write(self, out: Path) -> SspExport:
        model = self.sc.model
        root = self.etree.Element(f"{{{NS['ssd']}}}SystemStructureDescription", nsmap=dict(NS),
                                  attrib={"name": model.name, "version": "1.0", "generationTool": "dynabrain"})
        system = self.el(root, "ssd:System", name=model.name, **({"description": model.description}
                                                                  if model.description else {}))
        elements = self.el(system, "ssd:Elements")
        for i, cfg in enumerate(model.modules):
            self._component(elements, i, cfg)
        connections = self.el(system, "ssd:Connections")
        for conn in self.world.connections:
            self._connection(connections, conn)
        for empty in (elements, connections):
            if not len(empty):
                system.remove(empty)
        if self.enumerations:  # (the SSD's order: System, Enumerations, ..., DefaultExperiment)
            kinds = self.el(root, "ssd:Enumerations")
            for name, items in self.enumerations.items():
                kind = self.el(kinds, "ssc:Enumeration", name=name)
                for item, value in items:
                    self.el(kind, "ssc:Item", name=item, value=str(value))
        duration_ns = self.sc.duration_ns
        experiment = self.el(root, "ssd:DefaultExperiment", startTime="0.0", stopTime=repr(duration_ns / NS_PER_S))
        self._annotate(experiment, "World", step_ns=str(self.world.dt_ns), duration_ns=str(duration_ns),
                       seed=str(model.world.seed), history=str(model.world.history))
        if self.problems:
            raise SSPError(self.problems, "scenario")
        validated = _validate(root)
        self._zip(root, out)
        return SspExport(out, "1.0", tuple(m.name for m in model.modules), self.connections,
                         tuple(sorted(self.resources.values())), tuple(self._left_out()), validated)

    def _annotate(self, parent: Any, what: str, **attrib: str) -> None:
        annotations = self.el(parent, "ssd:Annotations")
        annotation = self.el(annotations, "ssc:Annotation", type=ANNOTATION)
        self.el(annotation, f"db:{what}", **attrib)

    def _component(self, elements: Any, i: int, cfg: Any) -> None:
        module = self.world.modules[cfg.name]
        info = module.info
        comp = self.el(elements, "ssd:Component", name=cfg.name, type=FMU_TYPE, source=self._resource(info),
                       implementation="CoSimulation")
        connectors = self.el(comp, "ssd:Connectors")
        for sig in (*info.inputs, *info.outputs):
            for name in _names(sig, None) or ():
                conn = self.el(connectors, "ssd:Connector", name=name, kind=sig.kind)
                enumeration = self._enumeration(info, sig) if sig.fmi_type == "Enumeration" else None
                if enumeration is not None:
                    self.el(conn, "ssc:Enumeration", name=enumeration)
                else:
                    self.el(conn, f"ssc:{_SSC_TYPES.get(sig.type, 'Integer')}")
        if not len(connectors):
            comp.remove(connectors)
        values = []
        for key in cfg.params:
            values += self._param(module, key, ("modules", i, "params", key))
        if values:
            binding = self.el(self.el(comp, "ssd:ParameterBindings"), "ssd:ParameterBinding")
            pset = self.el(self.el(binding, "ssd:ParameterValues"), "ssv:ParameterSet", version="1.0", name=cfg.name)
            parameters = self.el(pset, "ssv:Parameters")
            for name, kind, text in values:
                self.el(self.el(parameters, "ssv:Parameter", name=name), f"ssv:{kind}", value=text)
        extra = {}
        if cfg.period is not None:
            extra["period_ns"] = str(parse_duration_ns(cfg.period))
        if cfg.isolate:
            extra["isolate"] = "true"
        if cfg.call_timeout is not None:
            extra["call_timeout_ns"] = str(parse_duration_ns(cfg.call_timeout, allow_frequency=False))
        if extra:
            self._annotate(comp, "Module", **extra)

    def _enumeration(self, info: Any, sig: Any) -> str | None:
        """The enumeration type of an FMU variable (its items written once under ``ssd:Enumerations``), or
        None where the model description does not say one."""
        from fmpy import read_model_description

        md = self._descriptions.get(info.path)
        if md is None:
            md = self._descriptions[info.path] = read_model_description(info.path, validate=False)
        variable = next((v for v in md.modelVariables if v.name == sig.name), None)
        kind = getattr(variable, "declaredType", None)
        items = getattr(kind, "items", None)
        if kind is None or not items:
            return None
        listed = [(item.name, int(item.value)) for item in items]
        if self.enumerations.setdefault(kind.name, listed) != listed:
            return None  # two FMUs, one name, other items: left as a number
        return kind.name

    def _resource(self, info: Any) -> str:
        if info.path not in self.resources:
            stem = f"{info.model_identifier}-fmi{info.version}"
            name, n = f"resources/{stem}.fmu", 1
            while name in self.resources.values():
                n += 1
                name = f"resources/{stem}-{n}.fmu"
            self.resources[info.path] = name
        return self.resources[info.path]

    def _param(self, module: Any, key: str, path: tuple[Any, ...]) -> list[tuple[str, str, str]]:
        sig = next(s for s in module.info.params if s.name == key)
        value = module.params[key]
        where = f"module {module.name!r}, parameter {key!r}"
        if sig.fmi_type == "Enumeration":
            self.problems.append(self.sc.source.problem(path, f"{where}: enumeration values are not exported (SSV "
                                                              "names an enumeration's items, dynabrain numbers them)"))
            return []
        if sig.shape and len(sig.vrs) == 1:
            self.problems.append(self.sc.source.problem(path, f"{where}: an FMI 3.0 array; SSV 1.0 values are "
                                                              "scalars"))
            return []
        items = list(value) if sig.shape else [value]
        names = _names(sig, None) or [key]
        out = []
        for name, item in zip(names, items, strict=True):
            if sig.type in ("real", "float32"):
                out.append((name, "Real", repr(float(item))))
            elif sig.type == "boolean":
                out.append((name, "Boolean", "true" if item else "false"))
            elif sig.type == "string":
                out.append((name, "String", str(item)))
            elif sig.type == "binary":
                out.append((name, "Binary", bytes(item).hex()))
            elif _INT32[0] <= int(item) <= _INT32[1]:
                out.append((name, "Integer", str(int(item))))
            else:
                self.problems.append(self.sc.source.problem(path, f"{where}: {int(item)} is beyond SSV's 32-bit "
                                                                  "Integer"))
        return out

    def _connection(self, parent: Any, conn: Any) -> None:
        ends = []
        for signal in (conn.src, conn.dst):
            module_name, _, port = signal.partition(".")
            sig, index = _port(self.world.modules[module_name].info, port)
            names = _names(sig, index)
            if names is None:
                self.problems.append(Problem(f"connection {conn}: {signal} is an element of the FMI 3.0 array "
                                             f"{sig.name!r}; SSP connects whole variables", self.sc.path))
                return
            ends.append((module_name, names))
        (a, outs), (b, ins) = ends
        if len(outs) != len(ins):
            self.problems.append(Problem(f"connection {conn}: FMI 2.0 scalars and an FMI 3.0 array; SSP connects "
                                         "variables one to one", self.sc.path))
            return
        for src, dst in zip(outs, ins, strict=True):
            xml = self.el(parent, "ssd:Connection", startElement=a, startConnector=src, endElement=b,
                          endConnector=dst)
            if conn.delay:
                self._annotate(xml, "Connection", delay="true")
            self.connections += 1

    def _left_out(self) -> list[str]:
        model = self.sc.model
        out = []
        for key, what in (("events", "events"), ("expect", "expectations")):
            items = getattr(model, key)
            if items:
                out.append(f"{what} ({len(items)}, {key}:): SSP describes a system, not a run")
        if model.select is not None:
            out.append("select: (no physics core)")
        if model.log.mcap is not None:
            out.append("log: (SSP has no output settings)")
        if model.world.realtime:
            out.append("world.realtime")
        return out

    def _zip(self, root: Any, out: Path) -> None:
        data = self.etree.tostring(root, pretty_print=True, xml_declaration=True, encoding="UTF-8")
        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=out.name, suffix=".part", dir=out.parent)
        os.close(fd)
        try:
            with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
                zf.writestr(SSD, data)
                for path, name in self.resources.items():
                    zf.write(path, name)
            os.replace(tmp, out)
        except BaseException:
            os.unlink(tmp)
            raise


def _port(info: Any, port: str) -> tuple[Any, int | None]:
    """The signal behind a module port: a block port or the element view ``name[i]`` of a vector."""
    for sig in (*info.inputs, *info.outputs):
        if port == sig.name:
            return sig, None
        if len(sig.shape) == 1 and port.startswith(f"{sig.name}[") and port.endswith("]"):
            return sig, int(port[len(sig.name) + 1:-1]) - 1
    raise DynabrainError(f"no port {port!r} in {info.label}")  # not reached: the world checked the connection


def _names(sig: Any, index: int | None) -> list[str] | None:
    """The FMI variable names (SSP connector names) of ``sig`` or of its element ``index``; None for an
    element of an FMI 3.0 array (one variable)."""
    if len(sig.vrs) > 1:
        return [f"{sig.name}[{i + 1}]" for i in range(len(sig.vrs))] if index is None else [f"{sig.name}[{index + 1}]"]
    return [sig.name] if index is None else None


def _validate(root: Any) -> bool:
    """Check the SSD, and each inline parameter set, against FMPy's copy of the SSP 1.0 schemas; False
    when FMPy ships none. Raises `SSPError` (a bug here) when they do not validate."""
    from lxml import etree

    try:
        from fmpy.ssp import ssd as fmpy_ssd
    except ImportError:
        return False
    schemas = Path(fmpy_ssd.__file__).parent / "schema"
    if not (schemas / "SystemStructureDescription.xsd").is_file():
        return False
    try:
        fmpy_ssd.validate_tree(root, "SystemStructureDescription.xsd")
        for pset in root.iter(f"{{{NS['ssv']}}}ParameterSet"):
            fmpy_ssd.validate_tree(etree.fromstring(etree.tostring(pset)), "SystemStructureParameterValues.xsd")
    except Exception as exc:
        raise SSPError([f"the SSD written does not validate against the SSP 1.0 schema: {exc}"], "export") from None
    return True
