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
against the SSP 1.0 schema it ships; an SSD other tools wrote that the schema refuses is read as it is,
the schema's words kept in the notes). What that reader leaves out is read here from the same XML:
the default experiment, the step (dynabrain's annotation, OSP's ``FixedStepAlgorithm`` of libcosim,
OMSimulator's ``FixedStepMaster``), connector units, transformations on connections, inline parameter
mappings and a component's ``implementation``.

Nested systems are made flat (component ``c`` of system ``s`` is module ``s_c``), and chains of
connections through systems' own connectors are followed to their component ends (`ssp_wiring`): the
whole system's parameter connectors give their bound values to the parameters they drive, its inputs
their values at t=0 (an event), and what stays free is said in the notes. A linear transformation on a
connection becomes a module between its ends (`modules.basic.Gain` with an offset); parameter mappings
(``.ssm``, or inline) rename and transform values. A loop of feedthrough FMUs that declare no
dependencies is broken by delaying the connection that goes back in the SSP's order, or iterated to
agreement (``loops="iterate"``); either is noted.

What dynabrain cannot run is refused, naming the file and the element: a component that is not an
FMU (a nested SSD or SSP), a Model Exchange FMU, signal dictionaries, unit conversions (a connection
between different units, a parameter value or a connector in another unit than the FMU's variable),
transformations other than linear ones, two outputs driving one chain, enumeration values, start values
of inputs. Parameter names that match no variable are ignored, as SSP says, and listed in the notes.

Written SSPs are SSD version 1.0 (the namespaces ``http://ssp-standard.org/SSP1/...``, which SSP 2.0
keeps): everything written is in SSP 1.0, SSP 2.0 readers read 1.0 files, and FMPy's reader and
schemas take 1.x only. Each SSD is checked against FMPy's copy of the SSP 1.0 schemas before it is
written. What SSP cannot say and a round trip needs (the step in integer nanoseconds, seed, history,
module periods, ``isolate``, ``delay`` on a connection) goes into annotations of type
``org.dynabrain.scenario``, which other tools ignore. Reading is here, writing in `ssp_export`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..kernel.errors import DynabrainError, Problem
from ..kernel.units import NS_PER_S

SSD = "SystemStructure.ssd"
NS = {"ssd": "http://ssp-standard.org/SSP1/SystemStructureDescription",
      "ssc": "http://ssp-standard.org/SSP1/SystemStructureCommon",
      "ssv": "http://ssp-standard.org/SSP1/SystemStructureParameterValues",
      "ssm": "http://ssp-standard.org/SSP1/SystemStructureParameterMapping",
      "db": "urn:dynabrain:ssp:1"}
ANNOTATION = "org.dynabrain.scenario"
"""The type of dynabrain's annotations (world, module and connection settings SSP has no words for)."""
FMU_TYPE = "application/x-fmu-sharedlibrary"
SSV_TYPE = "application/x-ssp-parameter-set"


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
               fmu_dir: str | os.PathLike[str] | None = None, check: bool = True, loops: str = "delay") -> SspImport:
    """Write the scenario of the SSP at ``ssp`` to ``scenario`` (default: beside the SSP, ``.yaml``)
    and extract its FMUs to ``fmu_dir`` (default: a folder named after the scenario, beside it).
    ``check``: build the scenario once (every FMU loaded, every connection checked) and raise if it
    does not validate. ``loops``: how a loop of feedthrough FMUs that declare no dependencies is broken:
    ``"delay"`` (a connection of it delayed) or ``"iterate"`` (iterated to agreement each step). Raises
    `SSPError` naming the file and each element at fault."""
    ssp = Path(ssp)
    out = Path(scenario) if scenario is not None else ssp.with_suffix(".yaml")
    folder = Path(fmu_dir) if fmu_dir is not None else out.with_suffix("")
    result = read_ssp(ssp, folder, scenario_dir=out.parent, loops=loops)
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
             scenario_dir: str | os.PathLike[str] = ".", loops: str = "delay") -> SspImport:
    """The scenario of the SSP at ``ssp`` as plain data (not written), its FMUs extracted to
    ``fmu_dir`` and named relative to ``scenario_dir``. Raises `SSPError`."""
    if loops not in ("delay", "iterate"):
        raise SSPError([f"{ssp}: loops={loops!r}: 'delay' or 'iterate'"])
    from .ssp_read import Reader

    return Reader(Path(ssp), Path(fmu_dir), Path(scenario_dir), loops).read()


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
