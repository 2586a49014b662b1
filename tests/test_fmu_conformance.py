"""The conformance FMUs of fmus/conformance/, built here from their sources: every FMI type on the bus
or as a parameter (exact conversions, values that do not fit refused naming the variable), an FMU
that asks to end the simulation, failures of an FMU that cannot restore its state (unusable, or
restarted from scratch when isolated), non-finite outputs, the start time, and `fmu check`."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.fmu import (
    FMUCallError,
    FMUDiscardError,
    FMUError,
    FMUTerminatedError,
    FMUUnusableError,
    load_fmu_info,
    make_fmu_module,
)
from dynabrain.orchestrator.fmu.build import build_fmu, package_fmu
from dynabrain.orchestrator.fmu.check import check_fmu
from dynabrain.orchestrator.kernel.errors import NonFiniteOutputError, RollbackError
from dynabrain.orchestrator.kernel.world import World

ROOT = Path(__file__).resolve().parents[1]
CONFORMANCE = ROOT / "fmus" / "conformance"
NUMBERS = ("f64", "f32", "i8", "u8", "i16", "u16", "i32", "u32", "i64", "u64")

pytestmark = pytest.mark.usefixtures("fmu_cache")  # FMUs built here go to a cache of this module's own


def module(name: str, fmu: str, **kw):
    params = kw.pop("params", {})
    return make_fmu_module(name, f"fmus/conformance/{fmu}", base_dir=str(ROOT), params=params, targets=[], **kw)


def value_references(m) -> dict[str, int]:
    from fmpy import read_model_description

    return {v.name: v.valueReference for v in read_model_description(m.info.path).modelVariables}


def repack(fmu: Path, dest: Path, edit) -> Path:
    """A copy of ``fmu`` with its model description edited by ``edit`` (text -> text)."""
    with zipfile.ZipFile(fmu) as zf:
        xml = zf.read("modelDescription.xml").decode()
        lib_name = next(n for n in zf.namelist() if n.startswith("binaries/"))
        lib = dest.parent / Path(lib_name).name
        lib.write_bytes(zf.read(lib_name))
    return package_fmu(dest, edit(xml), {str(Path(lib_name).parent): lib})


# -- every type ---------------------------------------------------------------------------------------------
def test_every_fmi3_type_is_on_the_bus_exactly_and_strings_and_binaries_are_listed_once(caplog):
    with caplog.at_level("WARNING", logger="dynabrain.fmu"):
        m = module("a", "alltypes", params={"label": "L", "key": "0102", "offset": 5, "level": 2})
        module("b", "alltypes")
    listed = [r.getMessage() for r in caplog.records if "not on the bus" in r.getMessage()]
    assert len(listed) == 1 and all(f"{v} (" in listed[0] for v in ("text_in", "text_out", "blob_in", "blob_out"))
    assert [p.name for p in m.inputs()][:3] == ["f64_in", "f32_in", "i8_in"]  # reals first, then kind by kind
    assert "text_in" not in {p.name for p in m.inputs()} and isinstance(m.params["key"], bytes)
    with World(step="1ms") as w:
        w.add_module(m)
        start = {n: w.get(f"a.{n}_out") for n in NUMBERS}
        assert start == {"f64": 0.5, "f32": 0.25, "i8": -8, "u8": 8, "i16": -16, "u16": 16, "i32": -32, "u32": 32,
                         "i64": -59, "u64": 64}  # the start values crossed the FMU (and i64 got offset 5)
        assert (w.get("a.flag_out"), w.get("a.mode_out"), w.get("a.level_out")) == (1.0, 2.0, 2.0)
        extremes = {"i8": -128, "u8": 255, "i16": -32768, "u16": 65535, "i32": -2**31, "u32": 2**32 - 1,
                    "i64": -2**53, "u64": 2**53, "f64": 0.1, "f32": 0.1}
        for name, value in extremes.items():
            w.set(f"a.{name}_in", value)
        w.set("a.mode_in", 3)
        w.tick()
        for name, value in extremes.items():
            expected = {"i64": -2**53 + 5, "f32": float(np.float32(0.1))}.get(name, value)
            assert w.get(f"a.{name}_out") == expected, name
        assert w.get("a.mode_out") == 3
        api = m._session.api
        vrs = value_references(m)
        assert api.get_strings(np.array([vrs["text_out"]], dtype=np.uint32)) == ["L:hello"]
        assert api.get_binaries(np.array([vrs["blob_out"]], dtype=np.uint32)) == [b"\x01\x02foo"]
        w.set("a.label", "new")  # a tunable string parameter, at run time
        w.tick()
        assert api.get_strings(np.array([vrs["text_out"]], dtype=np.uint32)) == ["new:hello"]


@pytest.mark.parametrize(("port", "value", "why"), [
    ("i8_in", 300, r"input i8_in = 300 does not fit Int8 \(-128 to 127\)"),
    ("u8_in", -1, r"input u8_in = -1 does not fit UInt8 \(0 to 255\)"),
    ("i32_in", np.nan, r"input i32_in = nan does not fit Int32"),
    ("i64_in", 2.0**53 + 2, r"input i64_in = 9\.0072e\+15 does not fit Int64 \(-9007199254740992 to "
                            r"9007199254740992\)"),
    ("f32_in", 1e39, r"input f32_in = 1e\+39 is beyond the range of a Float32"),
])
def test_an_input_that_does_not_fit_its_type_fails_the_tick_naming_it(port, value, why):
    with World(step="1ms") as w:
        w.add_module(module("a", "alltypes"))
        w.tick(2)
        w.set(f"a.{port}", value)
        with pytest.raises(FMUCallError, match=rf"module 'a': fmi3Set\w+\(\) at tick 2 failed: {why}"):
            w.tick()
        w.set(f"a.{port}", 1)
        w.tick()  # the FMU was never called with the value: it goes on
        assert w.get(f"a.{port.replace('_in', '_out')}") == 1


def test_a_64_bit_output_beyond_2_53_fails_its_tick_and_the_fmu_is_restored():
    with World(step="1ms") as w:
        w.add_module(module("a", "alltypes"))
        w.tick()
        w.set("a.offset", 2**60)
        with pytest.raises(FMUCallError, match=r"fmi3GetInt64\(\) at tick 1 failed: output i64_out = "
                                               r"1152921504606846912 is beyond 2\^53"):
            w.tick()
        w.set("a.offset", 0)
        w.set("a.i64_in", 7)
        w.tick()
        assert w.get("a.i64_out") == 7


def test_64_bit_variables_that_declare_values_beyond_2_53_are_refused_at_load(tmp_path):
    built = build_fmu(CONFORMANCE / "alltypes", 3)
    declared = 'name="i64_in" valueReference="17" causality="input" variability="discrete" start="-64"'
    big = repack(built, tmp_path / "big.fmu",
                 lambda x: x.replace(declared, declared.replace('"-64"', '"1152921504606846976"')))
    with pytest.raises(FMUError, match=r"big\.fmu: Int64 input 'i64_in' declares start=1152921504606846976, beyond "
                                       r"2\^53"):
        load_fmu_info(str(big))


def test_an_fmu_with_no_input_or_output_the_bus_can_take_is_refused(tmp_path):
    folder = tmp_path / "words"
    folder.mkdir()
    (folder / "fmu.yaml").write_text("name: words\nfmi: [2]\nvariables:\n"
                                     "  - {name: said, type: string, causality: input}\n"
                                     "  - {name: heard, type: string, causality: output}\n")
    (folder / "words.c").write_text('#include <string.h>\n#include "fmu_model.h"\n'
                                    "int model_init(ModelData *m) { strcpy(m->heard, m->said); return MODEL_OK; }\n"
                                    "int model_step(ModelData *m, double h) { (void)h; return model_init(m); }\n")
    with pytest.raises(FMUError, match=r"words.*none of its inputs and outputs can be on the bus: said \(input, "
                                       r"String: not on the bus\), heard \(output, String: not on the bus\)"):
        make_fmu_module("w", str(folder), base_dir=".", params={}, targets=[])


@pytest.mark.parametrize("version", [2, 3])
def test_fmi2_types_and_enumerations_in_both_versions(version):
    m = module("e", f"fmi2types@fmi{version}", params={"label": "X", "mode": 3})
    with World(step="1ms") as w:
        w.add_module(m)
        assert (w.get("e.n_out"), w.get("e.flag_out"), w.get("e.mode_out"), w.get("e.mode_param_out")) == (-3, 1, 2, 3)
        w.set("e.n_in", 2**31 - 1)
        w.set("e.mode_in", 1)
        w.set("e.flag_in", 0)
        w.tick()
        assert (w.get("e.n_out"), w.get("e.flag_out"), w.get("e.mode_out")) == (2**31 - 1, 0, 1)
        vrs = value_references(m)
        assert m._session.api.get_strings(np.array([vrs["text_out"]], dtype=np.uint32)) == ["X:hi"]


def test_every_type_rolls_back_and_forks_bit_for_bit_in_process_and_isolated():
    runs = []
    for isolate in (False, True):
        with World(step="1ms") as w:
            w.add_module(module("a", "alltypes", isolate=isolate, params={"label": "L"}))
            rows = []
            for k in range(6):
                w.set("a.i16_in", k * 1000 - 3000)
                w.set("a.f32_in", k / 3)
                w.tick()
                rows.append(w.snapshot().bus.copy())
            w.backtick(3)
            w.set("a.i16_in", 0)
            w.set("a.f32_in", 3 / 3)
            w.tick()
            assert np.array_equal(w.snapshot().bus, rows[3])
            f = w.fork()
            f.tick()
            w.tick()
            assert np.array_equal(f.snapshot().bus, w.snapshot().bus)
            f.close()
            runs.append(rows)
    assert all(np.array_equal(a, b) for a, b in zip(*runs, strict=True))


# -- terminate ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("version", [2, 3])
def test_an_fmu_that_asks_to_end_the_simulation_stops_the_world_there(version):
    with World(step="100ms") as w:
        w.add_module(module("s", f"stop@fmi{version}"))
        w.tick(9)  # FMU time 1.0 (its start time) to 1.9
        assert (w.get("s.t"), w.get("s.steps")) == (pytest.approx(1.9), 9)
        end = 9 if version == 2 else 10  # FMI 3.0 asks on an OK step: that step stands (test_fmi3_terminate)
        if version == 3:
            w.tick()
        for _ in range(2):  # asked again after the rollback: the FMU's state was restored
            with pytest.raises(FMUTerminatedError, match=rf"module 's': fmi{version}DoStep\(\) at tick {end} failed: "
                                                         r".*stop.*asked to end the simulation in its step from "
                                                         r"t=1\.9 s \(.*reached stop_at=2 s"):
                w.tick()
            assert w.tick_count == end and w.get("s.steps") == end


def test_outputs_line_up_with_fmpy_row_for_row_from_the_declared_start_time():
    from fmpy import simulate_fmu

    built = build_fmu(CONFORMANCE / "stop", 2)
    ref = simulate_fmu(str(built), stop_time=1.5, output_interval=0.1, start_values={"stop_at": 10.0})
    assert ref["time"][0] == 1.0 and len(ref) == 6
    with World(step="100ms") as w:
        w.add_module(module("s", "stop", params={"stop_at": 10.0}))
        rows = [(w.get("s.t"), w.get("s.steps"))]
        for _ in range(5):
            w.tick()
            rows.append((w.get("s.t"), w.get("s.steps")))
    assert [s for _, s in rows] == list(ref["steps"])
    assert np.allclose([t for t, _ in rows], ref["t"], rtol=0, atol=1e-12)
    with World(step="100ms") as w:  # the start time, overridden
        w.add_module(module("s", "stop", start_time=0.0, params={"stop_at": 10.0}))
        w.tick(2)
        assert w.get("s.t") == pytest.approx(0.2) and w.modules["s"].describe()["fmu"]["start_time"] == 0.0


def test_a_scenario_run_ends_where_the_fmu_asks(tmp_path):
    from dynabrain.orchestrator.scenario.model import load_scenario
    from dynabrain.orchestrator.scenario.runner import run_scenario

    scenario = tmp_path / "stop.yaml"
    scenario.write_text(f"name: stop\nworld: {{step: 100ms, duration: 5s, core: null}}\n"
                        f"modules:\n  - {{name: stopper, fmu: {CONFORMANCE / 'stop'}}}\n")
    result = run_scenario(load_scenario(scenario))
    assert result.ticks == 9 and result.error is None and result.ok  # a normal end (tests/test_terminate_run.py)
    assert result.ended_by == "stopper" and "asked to end the simulation at tick 9" in result.ended


# -- failures without a state to go back to -----------------------------------------------------------------
@pytest.mark.parametrize("version", [2, 3])
@pytest.mark.parametrize(("u", "error", "status"), [(1.5, FMUDiscardError, "Discard"), (2.5, FMUCallError, "Error"),
                                                     (3.5, FMUCallError, "Fatal")])
def test_an_fmu_that_cannot_restore_its_state_is_unusable_after_a_failure(version, u, error, status):
    m = module("n", f"nostate@fmi{version}")
    assert not m.CAPABILITIES.can_rollback
    with World(step="1ms") as w:
        w.add_module(m)
        w.set("n.u", 0.5)
        w.tick(4)
        w.set("n.u", u)
        with pytest.raises(error, match=rf"fmi{version}DoStep\(\) at tick 4 failed: fmi{version}{status}.*nostate.*"
                                        r"so it cannot be used any more"):
            w.tick()
        w.set("n.u", 0.5)
        with pytest.raises(FMUUnusableError, match=r"module 'n': .* at tick 4 failed: .*nostate.* (failed|reported a "
                                                   r"fatal error) earlier.*Remove the module"):
            w.tick()
        with pytest.raises(RollbackError, match=r"module\(s\) n cannot roll back"):
            w.backtick(1)
        assert w.tick_count == 4
        w.remove_module("n")
        w.tick()


@pytest.mark.parametrize("u", [1.5, 2.5, 3.5])
def test_an_isolated_fmu_without_state_is_restarted_from_scratch_after_a_failure(u, caplog):
    m = module("n", "nostate", isolate=True)
    with World(step="1ms") as w:
        w.add_module(m)
        w.set("n.u", 0.5)
        w.tick(4)
        assert w.get("n.y") == pytest.approx(0.002)
        w.set("n.u", u)
        with pytest.raises(FMUCallError, match=r"at tick 4 failed: .*its state is lost .*cannot serialize it.*: the "
                                               r"next step restarts it from scratch"):
            w.tick()
        w.set("n.u", 0.5)
        with caplog.at_level("WARNING", logger="dynabrain.fmu"):
            w.tick()
        assert w.get("n.y") == pytest.approx(0.0005) and w.tick_count == 5  # integrating again from 0
        assert len(m.restarts) == 1 and "its state before was lost" in caplog.text


# -- non-finite outputs -------------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["C step", "Python step", "isolated"])
def test_nan_and_infinite_fmu_outputs_fail_the_tick_they_appear(how):
    with World(step="1ms") as w:
        m = module("q", "nonfinite", isolate=how == "isolated")
        w.add_module(m)
        if how == "Python step":
            m._session.stepper.use_python()
            m.bind()
        w.tick(3)
        w.set("q.u", -1.0)
        with pytest.raises(NonFiniteOutputError, match=r"'q': step\(\) at tick 3 failed: output 'root' is NaN") as err:
            w.tick()
        assert (err.value.port, err.value.tick, w.tick_count) == ("root", 3, 3)
        w.set("q.u", 0.0)
        with pytest.raises(NonFiniteOutputError, match=r"output 'inverse' is inf"):
            w.tick()
        w.set("q.u", 4.0)
        w.tick()
        assert (w.get("q.root"), w.get("q.inverse"), w.tick_count) == (2.0, 0.25, 4)


# -- fmu check ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmu", ["alltypes", "fmi2types", "stop", "stop@fmi3", "nostate"])
def test_every_conformance_fmu_passes_its_check_within_the_ticks_asked(fmu, monkeypatch):
    reached = []
    tick = World.tick

    def counting(self, n=1):
        try:
            return tick(self, n)
        finally:
            reached.append(self.tick_count)

    monkeypatch.setattr(World, "tick", counting)
    report = check_fmu(str(CONFORMANCE / fmu), ticks=20)
    assert report.ok, str(report)
    assert max(reached) <= 20
    if fmu.startswith("stop"):  # (FMI 3.0 asks on an OK step: that step stands)
        end = 10 if fmu.endswith("fmi3") else 9
        assert any(f"asked to end the simulation at tick {end}" in n for n in report.notes)


def test_fmu_check_prints_each_problem_once_and_takes_ticks():
    runner = CliRunner()
    done = runner.invoke(app, ["fmu", "check", str(CONFORMANCE / "stop"), "--ticks", "30"])
    assert done.exit_code == 0, done.output
    assert "ok;" in done.output and done.output.count("asked to end the simulation at tick 9") == 1
    refused = runner.invoke(app, ["fmu", "check", str(CONFORMANCE / "stop"), "--ticks", "5"])
    assert refused.exit_code == 2 and "12" in refused.output
    failed = runner.invoke(app, ["fmu", "check", str(CONFORMANCE / "nonfinite")])  # seeded inputs below 0
    assert failed.exit_code == 1 and failed.output.count("output 'root' is NaN") == 1, failed.output
