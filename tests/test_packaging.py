"""Packaging and CLI conventions: the wheel holds the example scenarios (with their models and the FMU
sources they build), the FMU glue's C sources and the license, and builds without warnings; the runtime
dependencies are what the runtime imports; ``--version``, ``-v``/``-q``, a shipped scenario by name,
``dynabrain examples``."""

from __future__ import annotations

import logging
import os
import re
import shutil
import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.examples import resolve_scenario, shipped_scenarios
from dynabrain.orchestrator.cli.main import app

ROOT = Path(__file__).resolve().parent.parent
SKIP = (".venv", ".git", "build", "dist", "*.egg-info", "__pycache__", "runs", ".pytest_cache", ".ruff_cache",
        ".hypothesis", "*.mcap", "*.png")


def test_version_is_the_package_version():
    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"dynabrain {metadata.version('dynabrain')}"


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, str]:
    """An sdist and, from it, a wheel (``python -m build``) of a copy of the source tree; the build's output."""
    pytest.importorskip("build")
    tmp = tmp_path_factory.mktemp("build")
    src = tmp / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(*SKIP))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}  # (setuptools warns about it)
    proc = subprocess.run([sys.executable, "-m", "build", "--outdir", str(tmp / "dist"), str(src)], env=env,
                          capture_output=True, text=True, timeout=600)
    output = proc.stdout + proc.stderr
    if proc.returncode and re.search(r"Could not find a version|No matching distribution|connection", output, re.I):
        pytest.skip("the build's isolated environment needs setuptools from an index that cannot be reached")
    assert proc.returncode == 0, output[-3000:]
    wheel, = (tmp / "dist").glob("*.whl")
    return wheel, output


def test_the_wheel_holds_the_examples_the_c_sources_and_the_license(built):
    wheel, output = built
    # csrc and data folders too; a word "warning", not a file such as warning_log.py in the build's listing
    assert not [line for line in output.splitlines() if re.search(r"\bwarnings?\b", line, re.I)]
    names = set(zipfile.ZipFile(wheel).namelist())
    scenarios = sorted(ROOT.glob("scenarios/*.yaml"))
    assert scenarios and all(f"dynabrain/scenarios/{p.name}" in names for p in scenarios)
    assert all(f"dynabrain/scenarios/models/{p.name}" in names for p in ROOT.glob("scenarios/models/*.xml"))
    for path in scenarios:  # every FMU a shipped scenario builds is shipped beside it
        for module in yaml.safe_load(path.read_text()).get("modules") or []:
            if "fmu" in module:
                assert f"dynabrain/{module['fmu']}/fmu.yaml" in names, (path.name, module["fmu"])
    assert all(f"dynabrain/orchestrator/fmu/csrc/{p.name}" in names for p in ROOT.glob("orchestrator/fmu/csrc/*"))
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
    meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    runtime = [line.split(":", 1)[1].strip() for line in meta.splitlines()
               if line.startswith("Requires-Dist:") and "extra ==" not in line]
    assert "License-Expression: Apache-2.0" in meta
    assert not any(r.startswith(("mcap", "pytest", "websockets")) for r in runtime)  # the runtime never imports them
    assert any(r.startswith("zstandard") for r in runtime)  # the log writer and reader do


def test_license_is_the_apache_2_text():
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License\n                           Version 2.0, January 2004" in text
    assert "END OF TERMS AND CONDITIONS" in text and len(text.splitlines()) > 190


def test_a_shipped_scenario_runs_by_name(tmp_path, monkeypatch):
    shipped = shipped_scenarios()
    assert {"two_cubes", "humanoid_stand", "earthquake"} <= set(shipped)
    monkeypatch.chdir(tmp_path)  # nothing of that name here
    assert resolve_scenario(Path("two_cubes")) == shipped["two_cubes"] == resolve_scenario(Path("two_cubes.yaml"))
    (tmp_path / "two_cubes").write_text("a local file of that name wins")
    assert resolve_scenario(Path("two_cubes")) == Path("two_cubes")
    result = CliRunner().invoke(app, ["run", "bounce", "-q"])
    assert result.exit_code == 0, result.output
    listed = CliRunner().invoke(app, ["examples"])
    assert listed.exit_code == 0 and "two_cubes" in listed.output
    copied = CliRunner().invoke(app, ["examples", "--copy", str(tmp_path / "ex")])
    assert copied.exit_code == 0, copied.output
    assert (tmp_path / "ex/scenarios/models/humanoid.xml").exists() and (tmp_path / "ex/fmus/servo/fmu.yaml").exists()


@pytest.mark.parametrize(("flags", "level"), [([], logging.WARNING), (["-v"], logging.INFO),
                                              (["-vv"], logging.DEBUG), (["-q"], logging.ERROR)])
def test_verbosity_sets_dynabrains_log_level(flags, level):
    result = CliRunner().invoke(app, [*flags, "check", str(ROOT / "scenarios" / "two_cubes.yaml")])
    assert result.exit_code == 0, result.output
    assert logging.getLogger("dynabrain").level == level
