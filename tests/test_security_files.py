"""Issue 24, items 2 and 3: a model file and an FMU are read within limits.

A scene's model file must be a regular file (no device, FIFO or folder), read with a size bound, and its
bodies are counted with its includes and replicates before MuJoCo reads it (`scenario.modelfile`). An
FMU is opened and extracted with a cap on its expanded size and ratio, and no member may be written
outside its folder (`fmu.archive`). FMUs here are real, built from ``fmus/``.
"""

from __future__ import annotations

import os
import shutil
import zipfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.fmu import FMUError, archive, make_fmu_module
from dynabrain.orchestrator.fmu.build import build_fmu
from dynabrain.orchestrator.kernel.errors import ScenarioError
from dynabrain.orchestrator.scenario import limits, modelfile
from dynabrain.orchestrator.scenario.model import load_world

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()
BOX = '<body><freejoint/><geom type="box" size=".05 .05 .05" mass=".1"/></body>'


def problems_of(folder: Path, model: str) -> list:
    path = folder / "s.yaml"
    path.write_text(f"name: s\nworld: {{step: 2ms, duration: 10ms}}\nscene: {{model: {model}}}\n")
    with pytest.raises(ScenarioError) as caught:
        load_world(path)
    return caught.value.problems


def mjcf(worldbody: str, head: str = "") -> str:
    return f"<mujoco>{head}<worldbody>{worldbody}</worldbody></mujoco>"


# -- model files --------------------------------------------------------------------------------------------
def test_a_device_a_fifo_and_a_folder_are_refused_unread(tmp_path):
    fifo = tmp_path / "pipe.xml"
    os.mkfifo(fifo)  # opening it would wait for a writer forever
    for model, kind in (("/dev/zero", "a device"), ("pipe.xml", "a FIFO"), (".", "a folder")):
        (problem,) = problems_of(tmp_path, model)
        assert problem.line == 3 and problem.field == "scene.model", problem
        assert f"is {kind}, not a regular file" in problem.message


def test_a_link_to_a_device_is_followed_and_refused(tmp_path):
    (tmp_path / "robot.xml").symlink_to("/dev/zero")
    (problem,) = problems_of(tmp_path, "robot.xml")
    assert "is a device" in problem.message


def test_a_model_file_above_max_model_bytes_is_refused_unread(tmp_path):
    with open(tmp_path / "huge.xml", "wb") as fh:  # sparse: no disk used
        fh.truncate(limits.MAX_MODEL_BYTES + 1)
    (problem,) = problems_of(tmp_path, "huge.xml")
    assert "MAX_MODEL_BYTES" in problem.message


def test_replicated_bodies_are_counted_before_mujoco_reads_them(tmp_path, monkeypatch):
    import mujoco

    def refuse(*args, **kwargs):
        raise AssertionError("MuJoCo read the model")

    monkeypatch.setattr(mujoco.MjSpec, "from_file", refuse)
    monkeypatch.setattr(mujoco.MjModel, "from_xml_path", refuse)
    grid = f'<replicate count="150" offset=".1 0 0"><replicate count="150" offset="0 .1 0">{BOX}</replicate>' \
           "</replicate>"
    (tmp_path / "grid.xml").write_text(mjcf(grid))
    (problem,) = problems_of(tmp_path, "grid.xml")
    assert "at least 22500 bodies" in problem.message and "MAX_BODIES" in problem.message
    bomb = f'<replicate count="1000"><replicate count="1000"><replicate count="1000">{BOX}</replicate>' \
           "</replicate></replicate>"  # a billion bodies: the count stops at the first replicate past the limit
    (tmp_path / "bomb.xml").write_text(mjcf(bomb))
    (problem,) = problems_of(tmp_path, "bomb.xml")
    assert "MAX_BODIES" in problem.message


def test_included_bodies_are_counted_and_includes_are_regular_files(tmp_path):
    (tmp_path / "part.xml").write_text(f"<mujoco>{BOX * 6000}</mujoco>")
    twice = '<include file="part.xml"/><include file="part.xml"/>'
    (tmp_path / "two.xml").write_text(mjcf(twice))
    (problem,) = problems_of(tmp_path, "two.xml")
    assert "at least 10001 bodies" in problem.message
    (tmp_path / "dev.xml").write_text(mjcf('<include file="/dev/zero"/>'))
    (problem,) = problems_of(tmp_path, "dev.xml")
    assert "included file '/dev/zero' is a device" in problem.message
    (tmp_path / "loop.xml").write_text(mjcf('<include file="loop.xml"/>'))
    (problem,) = problems_of(tmp_path, "loop.xml")
    assert "MAX_INCLUDE_DEPTH" in problem.message


def test_an_asset_that_is_a_fifo_is_refused(tmp_path):
    (tmp_path / "meshes").mkdir()
    os.mkfifo(tmp_path / "meshes" / "arm.stl")
    head = '<compiler meshdir="meshes"/><asset><mesh name="arm" file="arm.stl"/></asset>'
    (tmp_path / "m.xml").write_text(mjcf(BOX, head))
    (problem,) = problems_of(tmp_path, "m.xml")
    assert "mesh file" in problem.message and "is a FIFO" in problem.message


def test_entities_are_refused(tmp_path):
    (tmp_path / "e.xml").write_text('<!DOCTYPE m [<!ENTITY a "aaaa">]>' + mjcf(BOX))
    (problem,) = problems_of(tmp_path, "e.xml")
    assert "DOCTYPE" in problem.message


def test_shipped_model_files_count_as_mujoco_counts_them():
    import mujoco

    models = [*sorted((ROOT / "scenarios" / "models").glob("*.xml")), ROOT / "scenarios" / "models" / "arm.urdf"]
    for path in models:  # (a URDF's links joined by fixed joints are fused into one body: never fewer)
        counted, made = modelfile.count_bodies(str(path)), mujoco.MjModel.from_xml_path(str(path)).nbody - 1
        assert counted == made if path.suffix == ".xml" else counted >= made, path.name


def test_check_refuses_a_replicated_model_with_its_line(tmp_path):
    grid = f'<replicate count="101"><replicate count="100">{BOX}</replicate></replicate>'
    (tmp_path / "g.xml").write_text(mjcf(grid))
    (tmp_path / "s.yaml").write_text("name: s\nscene: {model: g.xml}\n")
    done = runner.invoke(app, ["check", str(tmp_path / "s.yaml")])
    assert done.exit_code == 2 and "s.yaml:2 [scene.model]" in done.output and "MAX_BODIES" in done.output


# -- FMU archives -------------------------------------------------------------------------------------------
pytestmark = pytest.mark.usefixtures("fmu_cache")


@pytest.fixture(scope="module")
def good_fmu() -> Path:
    return build_fmu(ROOT / "fmus" / "passthrough", 2)


def repacked(good: Path, dest: Path, extra: dict[str, bytes]) -> Path:
    """A copy of ``good`` with ``extra`` members added (deflated)."""
    shutil.copy(good, dest)
    with zipfile.ZipFile(dest, "a", zipfile.ZIP_DEFLATED) as zf:
        for name, data in extra.items():
            zf.writestr(zipfile.ZipInfo(name), data, compress_type=zipfile.ZIP_DEFLATED)
    return dest


def test_a_zip_bomb_is_refused_before_anything_is_extracted(good_fmu, tmp_path):
    bomb = repacked(good_fmu, tmp_path / "bomb.fmu", {"resources/zeros.bin": bytes(64 * 1024 * 1024)})
    assert bomb.stat().st_size < 2 * 1024 * 1024
    with pytest.raises(FMUError, match=r"'resources/zeros.bin' expands \d+ times .* \(MAX_RATIO\): a zip bomb"):
        make_fmu_module("m", str(bomb), base_dir=".", params={}, targets=[])


def test_an_fmu_above_max_fmu_bytes_is_refused(good_fmu, tmp_path, monkeypatch):
    monkeypatch.setattr(archive, "MAX_FMU_BYTES", 4 * 1024 * 1024)
    big = repacked(good_fmu, tmp_path / "big.fmu", {"resources/noise.bin": os.urandom(5 * 1024 * 1024)})
    with pytest.raises(FMUError, match=r"expands to more than 4194304 bytes \(MAX_FMU_BYTES\)"):
        make_fmu_module("m", str(big), base_dir=".", params={}, targets=[])


@pytest.mark.parametrize("name", ["../../escaped.txt", "/tmp/escaped.txt", "resources/..\\..\\x.txt"])
def test_a_member_outside_the_folder_is_refused(good_fmu, tmp_path, name):
    slip = repacked(good_fmu, tmp_path / "slip.fmu", {name: b"gotcha"})
    with pytest.raises(FMUError, match="outside the FMU's folder"):
        make_fmu_module("m", str(slip), base_dir=".", params={}, targets=[])
    assert not (tmp_path.parent / "escaped.txt").exists()


def test_extraction_writes_what_the_archive_holds(good_fmu, tmp_path):
    archive.extract(good_fmu, str(tmp_path / "x"), "FMU passthrough")
    with zipfile.ZipFile(good_fmu) as zf:
        for info in zf.infolist():
            if not info.is_dir():
                assert (tmp_path / "x" / info.filename).read_bytes() == zf.read(info)
    module = make_fmu_module("m", str(good_fmu), base_dir=".", params={}, targets=[])
    module.close()


def test_an_fmu_that_is_a_fifo_or_a_device_is_refused_unopened(tmp_path):
    os.mkfifo(tmp_path / "pipe.fmu")  # opening it would wait for a writer forever
    for ref, kind in ((str(tmp_path / "pipe.fmu"), "a FIFO"), ("/dev/zero", "a device")):
        with pytest.raises(FMUError, match=f"is {kind}, not a file"):
            make_fmu_module("m", ref, base_dir=".", params={}, targets=[])


def test_a_scenario_that_is_a_fifo_or_a_device_is_refused_unread(tmp_path):
    os.mkfifo(tmp_path / "s.yaml")
    for path in (tmp_path / "s.yaml", "/dev/zero"):
        done = runner.invoke(app, ["check", str(path)])
        assert done.exit_code == 2 and "not a regular file" in done.output, done.output
