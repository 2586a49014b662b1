"""SSP in and out: a scenario of FMUs exported and imported back runs bit for bit like the original,
FMPy reads the export, a foreign SSP (an .ssv file, system-level bindings, OMSimulator's step) imports,
and bad SSPs and scenarios SSP cannot hold are refused naming the file and the element."""

from __future__ import annotations

import zipfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.scenario import load_world
from dynabrain.orchestrator.scenario.ssp import SSD, SSPError, export_ssp, import_ssp

pytestmark = pytest.mark.usefixtures("fmu_cache")  # FMUs built here go to a cache of this module's own

FMUS = Path(__file__).resolve().parent.parent / "fmus"
CHAIN = f"""\
name: ssp_chain
world: {{step: 1ms, duration: 200ms, core: null, seed: 3}}
modules:
  - {{name: floor, fmu: {FMUS}/moving_floor@fmi3, params: {{amplitude: 0.1, frequency: 3Hz, ramp: 20ms}}}}
  - {{name: filt, fmu: {FMUS}/sensor_filter, period: 2ms, params: {{cutoff: 15Hz, sigma: 0.001, seed: 7}}}}
  - {{name: p1, fmu: {FMUS}/passthrough, params: {{gain: -2.5}}}}
  - {{name: p2, fmu: {FMUS}/passthrough}}
  - {{name: a1, fmu: {FMUS}/passthrough@fmi3, params: {{gain: 0.5}}}}
  - {{name: a2, fmu: {FMUS}/passthrough@fmi3}}
connect:
  - [floor.position, "filt.u[1]"]
  - ["filt.y[1]", floor.q, {{delay: true}}]
  - [p1.y, p2.u]
  - ["p2.y[1]", "p1.u[2]", {{delay: true}}]
  - [a1.y, a2.u]
expect:
  - {{that: "abs(floor.position) < 0.2"}}
"""


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ssp")
    (folder / "chain.yaml").write_text(CHAIN)
    result = export_ssp(folder / "chain.yaml", folder / "chain.ssp")
    return folder, result


def test_round_trip_runs_bit_for_bit(exported, tmp_path):
    folder, result = exported
    assert result.version == "1.0" and result.validated and result.connections == 8  # p1.y -> p2.u: 4 scalars
    assert result.left_out == ("expectations (1, expect:): SSP describes a system, not a run",)
    back = import_ssp(result.path, tmp_path / "back.yaml")
    text = (tmp_path / "back.yaml").read_text()
    assert "core: null" in text and "period: 2ms" in text and "{delay: true}" in text
    original, imported = load_world(folder / "chain.yaml"), load_world(back.path)
    try:
        assert imported.signals == original.signals
        for _ in range(200):
            original.tick()
            imported.tick()
            assert imported.snapshot().bus.tobytes() == original.snapshot().bus.tobytes()
        assert original.get("filt.y")[0] != 0.0  # the filtered, noisy floor position went round the loop
    finally:
        original.close()
        imported.close()


def test_fmpy_reads_the_export(exported):
    from fmpy.ssp.ssd import read_ssd

    ssd = read_ssd(str(exported[1].path), validate=True)
    assert ssd.version == "1.0"
    assert [e.name for e in ssd.system.elements] == ["floor", "filt", "p1", "p2", "a1", "a2"]
    ends = {(c.startElement, c.startConnector, c.endElement, c.endConnector) for c in ssd.system.connections}
    assert ("p1", "y[4]", "p2", "u[4]") in ends and ("a1", "y", "a2", "u") in ends
    values = {p.name: p.value for p in ssd.system.elements[0].parameterBindings[0].parameterValues[0].parameters}
    assert values == {"amplitude": "0.1", "frequency": "3.0", "ramp": "0.02"}


def make_ssp(path: Path, system: str, files: dict[str, bytes], experiment: str = "") -> Path:
    ssd = (f'<?xml version="1.0" encoding="UTF-8"?>\n<ssd:SystemStructureDescription '
           'xmlns:ssd="http://ssp-standard.org/SSP1/SystemStructureDescription" '
           'xmlns:ssc="http://ssp-standard.org/SSP1/SystemStructureCommon" '
           'xmlns:ssv="http://ssp-standard.org/SSP1/SystemStructureParameterValues" '
           'xmlns:ssm="http://ssp-standard.org/SSP1/SystemStructureParameterMapping" '
           f'name="foreign" version="1.0">{system}{experiment}</ssd:SystemStructureDescription>')
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(SSD, ssd)
        for name, data in files.items():
            zf.writestr(name, data)
    return path


def component(name: str, connectors: str = "", bindings: str = "", ctype: str = "") -> str:
    kind = f' type="{ctype}"' if ctype else ""
    return (f'<ssd:Component name="{name}" source="resources/pass.fmu"{kind}><ssd:Connectors>'
            '<ssd:Connector name="u[1]" kind="input"/><ssd:Connector name="y[1]" kind="output"/>'
            f'{connectors}</ssd:Connectors>{bindings}</ssd:Component>')


def params(*values: tuple[str, str, str]) -> str:
    items = "".join(f'<ssv:Parameter name="{n}"><ssv:{t} value="{v}"/></ssv:Parameter>' for n, t, v in values)
    return f'<ssv:ParameterSet version="1.0" name="set"><ssv:Parameters>{items}</ssv:Parameters></ssv:ParameterSet>'


def system(elements: str, connections: str = "", bindings: str = "", annotations: str = "") -> str:
    links = f"<ssd:Connections>{connections}</ssd:Connections>" if connections else ""
    return (f'<ssd:System name="root">{bindings}<ssd:Elements>{elements}</ssd:Elements>{links}'
            f'{annotations}</ssd:System>')


@pytest.fixture(scope="module")
def passthrough(exported):
    with zipfile.ZipFile(exported[1].path) as zf:
        return zf.read("resources/passthrough-fmi2.fmu")


def test_a_foreign_ssp_imports_with_ssv_files_system_bindings_and_its_step(passthrough, tmp_path):
    ssv = f'<?xml version="1.0"?>{params(("gain", "Real", "3.0"), ("nope", "Real", "1"))}'.replace(
        "<ssv:ParameterSet", '<ssv:ParameterSet xmlns:ssv="http://ssp-standard.org/SSP1/SystemStructureParameterValues"')
    on_a = ('<ssd:ParameterBindings><ssd:ParameterBinding source="resources/a.ssv"/></ssd:ParameterBindings>')
    on_system = ('<ssd:ParameterBindings><ssd:ParameterBinding prefix="b."><ssd:ParameterValues>'
                 f'{params(("gain", "Integer", "-2"))}</ssd:ParameterValues></ssd:ParameterBinding>'
                 '</ssd:ParameterBindings>')
    oms = ('<ssd:Annotations><ssc:Annotation type="org.openmodelica"><oms:Annotations xmlns:oms="urn:oms">'
           '<oms:SimulationInformation><oms:FixedStepMaster description="oms-ma" stepSize="0.002000"/>'
           '</oms:SimulationInformation></oms:Annotations></ssc:Annotation></ssd:Annotations>')
    # start and end name the input first: the FMUs' causalities give the direction
    links = '<ssd:Connection startElement="b" startConnector="u[1]" endElement="a" endConnector="y[1]"/>'
    path = make_ssp(tmp_path / "foreign.ssp", system(component("a", bindings=on_a) + component("b"), links, on_system,
                                                     oms),
                    {"resources/pass.fmu": passthrough, "resources/a.ssv": ssv.encode()},
                    '<ssd:DefaultExperiment startTime="0" stopTime="0.1"/>')
    result = import_ssp(path, tmp_path / "out" / "foreign.yaml")
    sc = result.scenario
    assert sc["world"] == {"core": None, "step": "2ms", "duration": "100ms"}
    assert [m["params"] for m in sc["modules"]] == [{"gain": 3.0}, {"gain": -2.0}]
    assert sc["modules"][0]["fmu"] == "foreign/resources/pass.fmu" and result.fmus[0].is_file()
    assert sc["connect"] == [["a.y[1]", "b.u[1]"]]
    assert any("'nope' matches no variable" in n for n in result.notes)
    assert any("OMSimulator" in n for n in result.notes)
    world = load_world(result.path)
    try:
        world.set("a.u[1]", 1.0)
        world.tick(2)
        assert world.get("b.y[1]") == -6.0
    finally:
        world.close()


@pytest.mark.parametrize("case", ["not a zip", "no ssd", "unknown connector", "not an FMU", "two drivers",
                                  "unit conversion", "missing ssv"])
def test_bad_ssps_name_the_file_and_the_element(case, passthrough, tmp_path):
    path = tmp_path / "bad.ssp"
    fmu = {"resources/pass.fmu": passthrough}
    link = '<ssd:Connection startElement="a" startConnector="y[1]" endElement="b" endConnector="{}"/>'
    expected = {"not a zip": "not a zip file", "no ssd": f"no {SSD}",
                "unknown connector": "connection 1 (a.y[1] -> b.nope): component 'b' has no connector 'nope'",
                "not an FMU": "component 'b': type 'application/x-ssp-package' is not an FMU",
                "two drivers": "a.y[1] and b.y[1] both drive one chain of connections",
                "unit conversion": "component 'a': connector 'y[1]' is in 'mm'",
                "missing ssv": "names a file the archive does not hold"}[case]
    if case == "not a zip":
        path.write_text("hello")
    elif case == "no ssd":
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr("resources/pass.fmu", passthrough)
    elif case == "unknown connector":
        make_ssp(path, system(component("a") + component("b"), link.format("nope")), fmu)
    elif case == "not an FMU":
        make_ssp(path, system(component("a") + component("b", ctype="application/x-ssp-package")), fmu)
    elif case == "two drivers":
        both = ('<ssd:Connection startElement="a" startConnector="y[1]" endElement="c" endConnector="u[1]"/>'
                '<ssd:Connection startElement="b" startConnector="y[1]" endElement="c" endConnector="u[1]"/>')
        make_ssp(path, system(component("a") + component("b") + component("c"), both), fmu)
    elif case == "unit conversion":
        unit = '<ssd:Connector name="gain" kind="parameter"><ssc:Real unit="mm"/></ssd:Connector>'
        make_ssp(path, system(component("a", unit).replace('name="y[1]" kind="output"/>',
                                                           'name="y[1]" kind="output"><ssc:Real unit="mm"/>'
                                                           '</ssd:Connector>'), ""), fmu)
    else:
        bindings = '<ssd:ParameterBindings><ssd:ParameterBinding source="resources/gone.ssv"/></ssd:ParameterBindings>'
        make_ssp(path, system(component("a", bindings=bindings)), fmu)
    with pytest.raises(SSPError) as info:
        import_ssp(path, tmp_path / "s.yaml")
    assert str(path) in str(info.value) and expected in str(info.value), str(info.value)
    assert not (tmp_path / "s.yaml").exists()


def test_export_refuses_what_ssp_cannot_hold_by_name(tmp_path):
    scenarios = Path(__file__).resolve().parent.parent / "scenarios"
    with pytest.raises(SSPError, match=r"fmu_servo.yaml:\d+ \[world.core\]: the physics core \(mujoco\) is not an FMU"):
        export_ssp(scenarios / "fmu_servo.yaml", tmp_path / "x.ssp")
    (tmp_path / "py.yaml").write_text(CHAIN.replace("  - {name: p2, fmu:", "  - {name: k, python: "
                                                    "dynabrain.modules.basic:Constant}\n  - {name: p2, fmu:"))
    with pytest.raises(SSPError, match=r"py.yaml:\d+ \[modules\[3\].python\]: module 'k' "
                                       r"\(dynabrain.modules.basic:Constant\) is a Python module"):
        export_ssp(tmp_path / "py.yaml", tmp_path / "x.ssp")
    (tmp_path / "el.yaml").write_text(CHAIN.replace("[a1.y, a2.u]", '["a1.y[2]", "a2.u[1]"]'))
    with pytest.raises(SSPError, match=r"a1.y\[2\] is an element of the FMI 3.0 array 'y'"):
        export_ssp(tmp_path / "el.yaml", tmp_path / "x.ssp")
    assert not (tmp_path / "x.ssp").exists()


def test_the_commands(exported, tmp_path):
    folder, _ = exported
    runner = CliRunner()
    out = runner.invoke(app, ["ssp", "export", str(folder / "chain.yaml"), "-o", str(tmp_path / "c.ssp")])
    assert out.exit_code == 0, out.output
    assert "SSD 1.0 (checked against the SSP 1.0 schema), 6 components, 8 connections, 4 FMUs" in out.output
    out = runner.invoke(app, ["ssp", "import", str(tmp_path / "c.ssp"), "-o", str(tmp_path / "c.yaml"), "--run"])
    assert out.exit_code == 0, out.output
    assert "6 FMU modules" in out.output and "all checks passed" in out.output
    (tmp_path / "junk.ssp").write_text("junk")
    out = runner.invoke(app, ["ssp", "import", str(tmp_path / "junk.ssp")])
    assert out.exit_code == 2 and "junk.ssp: not a zip file" in out.output


def test_nested_systems_are_made_flat_and_the_systems_own_connectors_carry_values(passthrough, tmp_path):
    """A nested system's component becomes module ``inner_c``; a chain through the nested system's input
    connects ``a`` to it; the whole system's parameter connector ``g`` (bound to 4) drives ``a.gain``."""
    inner = ('<ssd:System name="inner"><ssd:Connectors><ssd:Connector name="in" kind="input"/></ssd:Connectors>'
             f'<ssd:Elements>{component("c")}</ssd:Elements><ssd:Connections><ssd:Connection startElement="" '
             'startConnector="in" endElement="c" endConnector="u[1]"/></ssd:Connections></ssd:System>')
    links = ('<ssd:Connection startElement="a" startConnector="y[1]" endElement="inner" endConnector="in"/>'
             '<ssd:Connection startElement="" startConnector="g" endElement="a" endConnector="gain"/>')
    gain = '<ssd:Connector name="gain" kind="parameter"/>'
    bound = ('<ssd:ParameterBindings><ssd:ParameterBinding><ssd:ParameterValues>'
             f'{params(("g", "Real", "4.0"))}</ssd:ParameterValues></ssd:ParameterBinding></ssd:ParameterBindings>')
    root = system(component("a", gain) + inner, links, bound).replace(
        '<ssd:System name="root">', '<ssd:System name="root"><ssd:Connectors><ssd:Connector name="g" '
        'kind="parameter"/></ssd:Connectors>', 1)
    path = make_ssp(tmp_path / "nested.ssp", root, {"resources/pass.fmu": passthrough})
    result = import_ssp(path, tmp_path / "nested.yaml")
    sc = result.scenario
    assert sorted(m["name"] for m in sc["modules"]) == ["a", "inner_c"]
    assert sc["connect"] == [["a.y[1]", "inner_c.u[1]"]]
    assert next(m for m in sc["modules"] if m["name"] == "a")["params"] == {"gain": 4.0}
    world = load_world(result.path)
    try:
        world.set("a.u[1]", 1.0)
        world.tick(2)
        assert world.get("inner_c.u[1]") == 4.0
    finally:
        world.close()


def test_an_osp_step_and_a_loop_whose_fmus_declare_no_order(passthrough, tmp_path):
    """libcosim's step annotation is read; a loop of feedthrough FMUs is broken by delaying the connection
    that goes back in the SSP's order (said in the notes), or iterated to agreement when asked."""
    links = ('<ssd:Connection startElement="a" startConnector="y[1]" endElement="b" endConnector="u[1]"/>'
             '<ssd:Connection startElement="b" startConnector="y[1]" endElement="a" endConnector="u[1]"/>')
    osp = ('<ssd:Annotations><ssc:Annotation type="com.opensimulationplatform"><osp:FixedStepAlgorithm '
           'xmlns:osp="http://opensimulationplatform.com/SSP/OSPAnnotations" baseStepSize="0.0005"/>'
           '</ssc:Annotation></ssd:Annotations>')
    path = make_ssp(tmp_path / "loop.ssp", system(component("a") + component("b"), links, "", osp),
                    {"resources/pass.fmu": passthrough}, '<ssd:DefaultExperiment startTime="0" stopTime="0.01"/>')
    result = import_ssp(path, tmp_path / "loop.yaml")
    assert result.scenario["world"]["step"] == "500us"
    assert result.scenario["connect"] == [["a.y[1]", "b.u[1]"], ["b.y[1]", "a.u[1]", {"delay": True}]]
    assert any("b.y[1] -> a.u[1] is delayed to break a loop" in n for n in result.notes)
    assert any("OSP FixedStepAlgorithm" in n for n in result.notes)
    load_world(result.path).close()
    iterated = import_ssp(path, tmp_path / "loop_it.yaml", loops="iterate")
    assert iterated.scenario["iterate"] == [{"name": "ssp_loop", "modules": ["a", "b"]}]
    assert all(len(c) == 2 for c in iterated.scenario["connect"])
    load_world(iterated.path).close()


def test_a_linear_transformation_and_a_parameter_mapping(passthrough, tmp_path):
    link = ('<ssd:Connection startElement="a" startConnector="y[1]" endElement="b" endConnector="u[1]">'
            '<ssc:LinearTransformation factor="2.0" offset="1.0"/></ssd:Connection>')
    gain = '<ssd:Connector name="gain" kind="parameter"/>'
    mapped = ('<ssd:ParameterBindings><ssd:ParameterBinding><ssd:ParameterValues>'
              f'{params(("k", "Real", "3.0"))}</ssd:ParameterValues><ssd:ParameterMapping><ssm:ParameterMapping>'
              '<ssm:MappingEntry source="k" target="a.gain"/><ssm:MappingEntry source="k" target="b.gain">'
              '<ssc:LinearTransformation factor="2.0" offset="0.5"/></ssm:MappingEntry></ssm:ParameterMapping>'
              '</ssd:ParameterMapping></ssd:ParameterBinding></ssd:ParameterBindings>')
    path = make_ssp(tmp_path / "lt.ssp", system(component("a", gain) + component("b", gain), link, mapped),
                    {"resources/pass.fmu": passthrough})
    result = import_ssp(path, tmp_path / "lt.yaml")
    assert [m.get("params") for m in result.scenario["modules"][:2]] == [{"gain": 3.0}, {"gain": 6.5}], result.notes
    world = load_world(result.path)
    try:
        world.set("a.u[1]", 1.0)
        world.tick(2)
        assert world.get("b.u[1]") == 2.0 * 3.0 + 1.0  # a.y = 3 * 1, then the transformation
    finally:
        world.close()
