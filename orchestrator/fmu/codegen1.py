"""modelDescription.xml for FMI 1.0 co-simulation (stand-alone), from a checked fmu.yaml.

FMI 1.0 differs from 2.0 where an importer sees it: a parameter is ``variability="parameter"`` with
``causality="internal"`` (fixed: FMI 1.0 co-simulation sets only inputs after initialization, so a
tunable parameter is fixed here), a local is ``internal``, units are ``BaseUnit`` definitions, there
is no model structure (outputs depend on every input as far as an importer knows) and no FMU state.
Value references and vector elements are FMI 2.0's (`codegen.entries`).
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

from .codegen import GENERATOR, Entry, entries
from .spec import FmuSpec

_TYPE = {"real": "Real", "integer": "Integer", "boolean": "Boolean", "string": "String"}  # spec.FMI1_TYPES


def _fmt(kind: str, value: object) -> str:
    if kind == "boolean":
        return "true" if value else "false"
    if kind == "integer":
        return str(int(value))  # type: ignore[call-overload]
    if kind == "string":
        return str(value)
    return repr(float(value))  # type: ignore[arg-type]


def _variable(e: Entry) -> str:
    v = e.var
    if v.causality == "parameter":
        causality, variability = "internal", "parameter"
    else:
        causality = "internal" if v.causality == "local" else v.causality
        variability = "continuous" if v.variability == "continuous" else "discrete"
    text = f'name="{e.fmi_name}" valueReference="{e.vr}"'
    if v.description:
        text += f" description={quoteattr(v.description)}"
    text += f' variability="{variability}" causality="{causality}"'
    attrs = ""
    has_start = not (v.causality == "output" or (v.causality == "local" and not v.start_given))
    if has_start:
        value = v.start[e.element] if e.element is not None else v.start[0]
        attrs += f" start={quoteattr(_fmt(v.type, value))}"
        if v.causality != "input":
            attrs += ' fixed="true"'
    if v.type == "real" and v.unit and v.unit != "1":
        attrs += f" unit={quoteattr(v.unit)}"
    return f"    <ScalarVariable {text}><{_TYPE[v.type]}{attrs}/></ScalarVariable>"


def model_description1(spec: FmuSpec, guid: str) -> str:
    """modelDescription.xml for FMI 1.0 co-simulation (the model identifier is the FMU's name)."""
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<fmiModelDescription fmiVersion="1.0" modelName={quoteattr(spec.name)} modelIdentifier="{spec.name}"',
        f'  guid="{guid}" description={quoteattr(spec.description)} version={quoteattr(spec.version)}',
        f'  generationTool="{GENERATOR}" variableNamingConvention="structured" numberOfContinuousStates="0"',
        '  numberOfEventIndicators="0">',
    ]
    units = sorted({v.unit for v in spec.variables if v.type == "real" and v.unit and v.unit != "1"})
    if units:
        lines += ["  <UnitDefinitions>", *[f"    <BaseUnit unit={quoteattr(u)}/>" for u in units],
                  "  </UnitDefinitions>"]
    if spec.start_time is not None:
        lines.append(f'  <DefaultExperiment startTime="{spec.start_time!r}"/>')
    lines.append("  <ModelVariables>")
    lines += [_variable(e) for e in entries(spec, 1)]
    lines += ["  </ModelVariables>", "  <Implementation>", "    <CoSimulation_StandAlone>",
              '      <Capabilities canHandleVariableCommunicationStepSize="true" canHandleEvents="true"'
              ' canNotUseMemoryManagementFunctions="true"/>',
              "    </CoSimulation_StandAlone>", "  </Implementation>", "</fmiModelDescription>", ""]
    return "\n".join(lines)
