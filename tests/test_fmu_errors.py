"""Bad input to the FMU adapter, each case built for real (broken archives, broken descriptions,
binaries with symbols missing, FMUs that return fmiError / fmiFatal / fmiDiscard): every one gets
an error naming the FMU, the call and the cause, and the world it was meant for loses nothing."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.fmu import FMUCallError, FMUDiscardError, FMUError, FMUUnusableError, make_fmu_module
from dynabrain.orchestrator.fmu.build import build_fmu, compile_library, package_fmu
from dynabrain.orchestrator.kernel.errors import DynabrainError, ModuleError, ScenarioError
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario.model import load_scenario

FMUS = Path(__file__).resolve().parents[1] / "fmus"

FAULTY_VARS = """\
  - {name: u, causality: input}
  - {name: y, causality: output}
  - {name: x, causality: local}
  - {name: bad_init, type: boolean, causality: parameter, start: false}
"""
FAULTY_C = """
int model_init(ModelData *m) {
    if (m->bad_init) { fmu_log(m, MODEL_ERROR, "bad_init is set"); return MODEL_ERROR; }
    m->y = m->x; return MODEL_OK;
}
int model_step(ModelData *m, double h) {
    if (m->u > 3) { fmu_log(m, MODEL_FATAL, "u=%g melted the model", m->u); return MODEL_FATAL; }
    if (m->u > 2) { fmu_log(m, MODEL_ERROR, "u=%g is out of range", m->u); return MODEL_ERROR; }
    if (m->u > 1) { fmu_log(m, MODEL_DISCARD, "u=%g needs a smaller step", m->u); return MODEL_DISCARD; }
    m->x += m->u * h;
    m->y = m->x;
    return MODEL_OK;
}
"""


pytestmark = pytest.mark.usefixtures("fmu_cache")  # FMUs built here go to a cache of this module's own


@pytest.fixture(scope="module")
def faulty(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("src") / "faulty"
    folder.mkdir()
    (folder / "fmu.yaml").write_text(f"name: faulty\nfmi: [2, 3]\nvariables:\n{FAULTY_VARS}")
    (folder / "faulty.c").write_text('#include "fmu_model.h"\n' + FAULTY_C)
    return folder


@pytest.fixture(scope="module")
def good_fmu() -> Path:
    return build_fmu(FMUS / "passthrough", 2)


def module(ref: str | Path, name: str = "m", **params):
    return make_fmu_module(name, str(ref), base_dir=".", params=params, targets=[])


def description_of(fmu: Path) -> str:
    with zipfile.ZipFile(fmu) as zf:
        return zf.read("modelDescription.xml").decode()


def repack(fmu: Path, dest: Path, xml: str | None = None, platform: str | None = None) -> Path:
    """A copy of ``fmu`` with another description and/or its binary moved to another platform folder."""
    with zipfile.ZipFile(fmu) as zf:
        lib_name = next(n for n in zf.namelist() if n.startswith("binaries/"))
        lib = dest.parent / Path(lib_name).name
        lib.write_bytes(zf.read(lib_name))
    folder = platform or str(Path(lib_name).parent)
    return package_fmu(dest, xml if xml is not None else description_of(fmu), {folder: lib})


# -- files and descriptions ---------------------------------------------------------------------------------
def test_missing_file(tmp_path):
    with pytest.raises(FMUError, match=r"FMU 'nothing\.fmu' not found"):
        module("nothing.fmu")


def test_not_a_zip(tmp_path):
    bad = tmp_path / "text.fmu"
    bad.write_text("not an archive")
    with pytest.raises(FMUError, match=r"not a zip file"):
        module(bad)


def test_zip_without_model_description(tmp_path):
    bad = tmp_path / "empty.fmu"
    with zipfile.ZipFile(bad, "w") as zf:
        zf.writestr("readme.txt", "hello")
    with pytest.raises(FMUError, match=r"no modelDescription.xml"):
        module(bad)


def test_malformed_and_invalid_model_descriptions(tmp_path, good_fmu):
    xml = description_of(good_fmu)
    broken = repack(good_fmu, tmp_path / "broken.fmu", xml[: len(xml) // 2])
    with pytest.raises(FMUError, match=r"broken\.fmu.*modelDescription\.xml cannot be read"):
        module(broken)
    invalid = repack(good_fmu, tmp_path / "invalid.fmu", xml.replace('valueReference="1"', 'valueReference="one"', 1))
    with pytest.raises(FMUError, match=r"does not validate:\n  - .*line \d+"):
        module(invalid)
    old = repack(good_fmu, tmp_path / "old.fmu", xml.replace('fmiVersion="2.0"', 'fmiVersion="1.5"'))
    with pytest.raises(FMUError, match=r"1.5"):
        module(old)


def test_model_exchange_only_fmu_is_refused(tmp_path, good_fmu):
    xml = description_of(good_fmu)
    start = xml.index("<CoSimulation")
    end = xml.index("/>", start) + 2
    me = repack(good_fmu, tmp_path / "me.fmu", xml[:start] + '<ModelExchange modelIdentifier="passthrough"/>'
                + xml[end:])
    with pytest.raises(FMUError, match=r"me\.fmu.*model exchange FMU without co-simulation"):
        module(me)


def test_no_binary_for_this_platform(tmp_path, good_fmu):
    other = repack(good_fmu, tmp_path / "win.fmu", platform="binaries/win64")
    with pytest.raises(FMUError, match=r"no binary for this platform \(binaries/linux64/passthrough.so is "
                                       r"missing\); it has binaries for: win64"):
        module(other)


def test_missing_symbol_is_named_and_the_world_is_unchanged(tmp_path, good_fmu):
    src = tmp_path / "partial.c"
    src.write_text('#include "fmi2Functions.h"\nconst char *fmi2GetVersion(void) { return "2.0"; }\n'
                   'const char *fmi2GetTypesPlatform(void) { return "default"; }\n')
    lib = compile_library([src], tmp_path / "passthrough.so")
    fmu = package_fmu(tmp_path / "partial.fmu", description_of(good_fmu), {"binaries/linux64": lib})
    m = module(fmu, "partial")  # the description is fine: the binary is found out when the world loads it
    with World(step="1ms") as w:
        w.add_module(module(good_fmu, "ok"))
        with pytest.raises(FMUError, match=r"partial\.fmu.*lacks the FMI function fmi2\w+"):
            w.add_module(m)
        assert list(w.modules) == ["ok"]
        w.tick()


# -- wiring and parameters ------------------------------------------------------------------------------------
def test_parameter_errors_name_what_is_wrong(good_fmu):
    with pytest.raises(DynabrainError, match=r"'u' is an input of FMU .*, not a parameter; connect it"):
        module(good_fmu, u=1.0)
    with pytest.raises(DynabrainError, match=r"has no parameter 'gian'.*did you mean 'gain'"):
        module(good_fmu, gian=1.0)
    with pytest.raises(DynabrainError, match=r"parameter 'gain': 'loud' is not a number"):
        module(good_fmu, gain="loud")


def test_scenario_reports_unknown_variables_and_mismatches_with_lines(tmp_path):
    scenario = tmp_path / "bad.yaml"
    scenario.write_text(f"""\
name: bad
world: {{step: 2ms, duration: 0.1s, core: null}}
modules:
  - {{name: servo, fmu: {FMUS / "servo"}}}
  - {{name: floor, fmu: {FMUS / "moving_floor"}, params: {{amplitud: 0.1}}}}
  - {{name: filt, fmu: {FMUS / "sensor_filter"}}}
  - {{name: gone, fmu: {tmp_path / "missing"}}}
connect:
  - [servo.torque, filt.u]
  - [filt.y, servo.q]
  - ["filt.y[1]", "servo.q[1]"]
  - [filt.y, filt.u]
  - [servo.q, filt.u]
""")
    with pytest.raises(ScenarioError) as err:
        load_scenario(scenario).build()
    text = str(err.value)
    assert "bad.yaml:5 [modules[1].params]" in text and "did you mean 'amplitude'" in text
    assert "bad.yaml:7 [modules[3].fmu]" in text and "not found" in text
    assert "bad.yaml:9 [connect[0]]" in text and "module 'servo' has no output port 'torque'" in text
    assert "bad.yaml:10 [connect[1]]" in text and "shape mismatch" in text
    assert "bad.yaml:11 [connect[2]]" in text and "unit mismatch" in text
    assert "bad.yaml:12 [connect[3]]" in text and "algebraic loop: filt.y -> filt.u" in text
    assert "bad.yaml:13 [connect[4]]" in text and "servo.q is an input" in text


# -- calls that fail while the world runs ---------------------------------------------------------------------
@pytest.mark.parametrize("version", [2, 3])
def test_error_status_rolls_the_world_back_and_it_goes_on(faulty, version):
    with World(step="1ms") as w:
        w.add_module(module(f"{faulty}@fmi{version}", "f"))
        w.set("f.u", 0.5)
        w.tick(10)
        before = w.snapshot().bus
        w.set("f.u", 2.5)
        with pytest.raises(FMUCallError) as err:
            w.tick()
        e = err.value
        assert (e.module, e.call, e.tick) == ("f", f"fmi{version}DoStep", 10)
        assert f"fmi{version}Error" in str(e) and "u=2.5 is out of range" in str(e) and "faulty" in str(e)
        assert w.tick_count == 10 and w.error is e
        w.set("f.u", 0.5)  # the FMU was restored out of its error state with the tick's saved state
        w.tick()
        assert w.get("f.y") == pytest.approx(before[w.structure.layout.slots["f.y"].start] + 0.0005)


@pytest.mark.parametrize("version", [2, 3])
def test_discarded_step_is_a_result_the_world_rolls_back_and_retries(faulty, version):
    with World(step="1ms") as w:
        w.add_module(module(f"{faulty}@fmi{version}", "f"))
        w.tick(3)
        w.set("f.u", 1.5)
        with pytest.raises(FMUDiscardError, match=f"fmi{version}Discard.*u=1.5 needs a smaller step") as err:
            w.tick()
        assert isinstance(err.value, ModuleError) and err.value.tick == 3 and w.tick_count == 3
        w.set("f.u", 1.0)
        w.tick()
        assert w.get("f.y") == pytest.approx(0.001)


def test_fatal_status_ends_the_instance_cleanly(faulty):
    w = World(step="1ms")
    w.add_module(module(faulty, "f"))
    w.tick(2)
    w.set("f.u", 5.0)
    with pytest.raises(FMUCallError, match=r"fmi2Fatal.*melted the model"):
        w.tick()
    w.set("f.u", 0.0)
    for _ in range(2):  # refused, naming the FMU, every time
        with pytest.raises(FMUUnusableError, match=r"module 'f': fmi2DoStep\(\) at tick 2 failed: .*faulty.* reported "
                           r"a fatal error earlier \(fmi2DoStep: fmi2Fatal.*melted.*\); no call is allowed on it but "
                           r"freeing it. Remove the module.*isolate: true"):
            w.tick()
    assert w.tick_count == 2
    w.remove_module("f")
    w.tick()
    w.close()  # no call reaches the dead instance; nothing crashes


def test_failed_initialization_leaves_the_world_as_it_was(faulty):
    with World(step="1ms") as w:
        w.tick(4)
        with pytest.raises(FMUCallError, match=r"fmi2ExitInitializationMode.*bad_init is set"):
            w.add_module(module(faulty, "f", bad_init=True))
        assert w.modules == {} and w.tick_count == 4
        w.add_module(module(faulty, "f"))
        w.tick()
        assert np.isfinite(w.get("f.y"))
