"""FMU authoring: fmu.yaml checking, building with the machine's C compiler, the content-hash cache
(rebuilt when sources change, never written into the source folder), the scaffold, the checker and
the ``dynabrain fmu`` commands."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.fmu import FMUBuildError, FMUError, make_fmu_module
from dynabrain.orchestrator.fmu.build import build_fmu
from dynabrain.orchestrator.fmu.check import check_fmu
from dynabrain.orchestrator.fmu.scaffold import new_fmu
from dynabrain.orchestrator.fmu.spec import load_spec
from dynabrain.orchestrator.kernel.world import World

FMUS = Path(__file__).resolve().parents[1] / "fmus"
runner = CliRunner()


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("DYNABRAIN_CACHE", str(tmp_path / "cache"))


def write(folder: Path, yaml: str, c: str | None = None, name: str = "model") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "fmu.yaml").write_text(yaml)
    if c is not None:
        (folder / f"{name}.c").write_text(c)
    return folder


LAG_C = """#include <math.h>
#include "fmu_model.h"
int model_init(ModelData *m) { m->y = m->u; return MODEL_OK; }
int model_step(ModelData *m, double h) { m->y += (1.0 - exp(-h / 0.1)) * (GAIN * m->u - m->y); return MODEL_OK; }
"""
LAG_YAML = """name: lag
fmi: [2, 3]
defines: {GAIN: 2}
variables:
  - {name: u, causality: input}
  - {name: y, causality: output}
"""


def test_spec_problems_are_all_reported_with_file_and_line(tmp_path):
    folder = write(tmp_path / "bad", """name: 2bad
defines: {N: 3}
variables:
  - {name: u, causality: input, size: M}
  - {name: flag, type: boolean, causality: output, variability: continuous}
  - {name: k, causality: parameter, size: N, start: [1, 2]}
  - {name: y, causality: output, depends: [k]}
  - {name: y, causality: output, colour: red}
""", "int x;")
    with pytest.raises(FMUBuildError) as err:
        load_spec(folder)
    text = str(err.value)
    assert "fmu.yaml:8 [variables[4].colour]" in text  # shape errors come first, alone
    (folder / "fmu.yaml").write_text((folder / "fmu.yaml").read_text().replace(", colour: red", ""))
    with pytest.raises(FMUBuildError) as err:
        load_spec(folder)
    text = str(err.value)
    for expected in ("fmu.yaml:1 [name]: name '2bad' must be a C identifier",
                     "fmu.yaml:4 [variables[0].size]: size 'M' is neither a number nor a name in defines",
                     "fmu.yaml:5 [variables[1].variability]: a boolean variable cannot be continuous",
                     "fmu.yaml:6 [variables[2].start]: start has 2 values for a size of 3",
                     "fmu.yaml:7 [variables[3].depends]: 'k' is not an input",
                     "fmu.yaml:8 [variables[4].name]: variable 'y' is declared twice"):
        assert expected in text, expected


def test_compiler_errors_name_the_file_and_line(tmp_path):
    folder = write(tmp_path / "lag", LAG_YAML, LAG_C.replace("return MODEL_OK; }\nint model_step",
                                                             "return MODEL_OK }\nint model_step"), "lag")
    with pytest.raises(FMUBuildError, match=r"(?s)compilation failed:\n.*lag\.c:3:\d+: error"):
        build_fmu(folder)


def test_cache_by_content_hash_rebuilds_on_change_and_never_writes_into_the_sources(tmp_path):
    folder = write(tmp_path / "lag", LAG_YAML, LAG_C, "lag")
    before = sorted(os.listdir(folder))
    first = build_fmu(folder)
    stamp = first.stat().st_mtime_ns
    assert build_fmu(folder) == first and first.stat().st_mtime_ns == stamp  # cached: not built again
    assert first.is_relative_to(tmp_path / "cache")
    fmi3 = build_fmu(folder, 3)
    assert fmi3 != first and "fmi3" in fmi3.name
    (folder / "fmu.yaml").write_text(LAG_YAML.replace("GAIN: 2", "GAIN: 3"))
    second = build_fmu(folder)
    assert second != first
    assert sorted(os.listdir(folder)) == before
    with zipfile.ZipFile(second) as zf:
        assert sorted(zf.namelist()) == ["binaries/linux64/lag.so", "modelDescription.xml"]
    with pytest.raises(FMUBuildError, match=r"FMI 3.0 is not among"):
        build_fmu(write(tmp_path / "only2", LAG_YAML.replace("[2, 3]", "[2]"), LAG_C, "lag"), 3)


def test_a_scenario_source_folder_is_rebuilt_when_its_sources_change(tmp_path):
    folder = write(tmp_path / "fmus" / "lag", LAG_YAML, LAG_C, "lag")

    def steady_output() -> float:
        with World(step="10ms") as w:
            w.add_module(make_fmu_module("lag", "fmus/lag", base_dir=str(tmp_path / "scenarios"), params={},
                                         targets=[]))
            w.set("lag.u", 1.0)
            w.tick(200)
            return w.get("lag.y")

    assert steady_output() == pytest.approx(2.0)
    (folder / "lag.c").write_text(LAG_C.replace("GAIN * m->u", "-GAIN * m->u"))
    assert steady_output() == pytest.approx(-2.0)


def test_builds_are_reproducible(tmp_path):
    folder = write(tmp_path / "lag", LAG_YAML, LAG_C, "lag")
    a = build_fmu(folder, output=tmp_path / "a.fmu")
    b = build_fmu(folder, output=tmp_path / "b.fmu", force=True)
    with zipfile.ZipFile(a) as za, zipfile.ZipFile(b) as zb:
        assert za.read("modelDescription.xml") == zb.read("modelDescription.xml")
        assert [i.date_time for i in za.infolist()] == [(1980, 1, 1, 0, 0, 0)] * 2


def test_scaffold_builds_and_passes_its_check_as_generated(tmp_path):
    folder = new_fmu("tank", tmp_path)
    assert sorted(os.listdir(folder)) == ["fmu.yaml", "tank.c"]
    for version in (2, 3):
        report = check_fmu(f"{folder}@fmi{version}")
        report.assert_ok()
    with pytest.raises(FMUError, match=r"exists and is not empty"):
        new_fmu("tank", tmp_path)
    with pytest.raises(FMUError, match=r"must be a C identifier"):
        new_fmu("9lives", tmp_path)


def test_the_checker_catches_state_kept_outside_the_model_data(tmp_path):
    leaky = write(tmp_path / "leaky", LAG_YAML, """#include "fmu_model.h"
static double hidden = 0.0; /* state the glue cannot save: a rollback cannot bring it back */
int model_init(ModelData *m) { m->y = 0.0; return MODEL_OK; }
int model_step(ModelData *m, double h) { hidden += h * m->u; m->y = hidden; return MODEL_OK; }
""", "leaky")
    report = check_fmu(str(leaky))
    assert not report.ok
    assert any("replay differs" in p or "not bit-identical" in p for p in report.problems), report.problems


def test_fmu_commands(tmp_path):
    result = runner.invoke(app, ["fmu", "new", "valve", "--dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    folder = tmp_path / "valve"
    result = runner.invoke(app, ["fmu", "build", str(folder), "-o", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert sorted(os.listdir(tmp_path / "out")) == ["valve-fmi2.fmu", "valve-fmi3.fmu"]
    result = runner.invoke(app, ["fmu", "check", str(tmp_path / "out" / "valve-fmi3.fmu")])
    assert result.exit_code == 0 and "ok; checked" in result.output and "FMI 3.0" in result.output
    result = runner.invoke(app, ["fmu", "check", str(FMUS / "moving_floor")])
    assert result.exit_code == 0, result.output
    (folder / "valve.c").write_text("this is not C")
    result = runner.invoke(app, ["fmu", "build", str(folder)])
    assert result.exit_code == 2 and "compilation failed" in result.output
    result = runner.invoke(app, ["fmu", "check", str(tmp_path / "missing.fmu")])
    assert result.exit_code == 2 and "not found" in result.output
    leaky = write(tmp_path / "leaky", LAG_YAML, "#include \"fmu_model.h\"\nstatic double s;\n"
                  "int model_init(ModelData *m) { m->y = 0; return MODEL_OK; }\n"
                  "int model_step(ModelData *m, double h) { s += h; m->y = s; return MODEL_OK; }\n", "leaky")
    result = runner.invoke(app, ["fmu", "check", str(leaky)])
    assert result.exit_code == 1 and "FAILED" in result.output
