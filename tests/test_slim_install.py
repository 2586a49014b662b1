"""A slim install: the base runs scenarios with MuJoCo, writes and verifies logs and imports the bridge
without any extra; a part whose extra is missing is refused by name, with the extra to install. Each
check runs in a process where the extras' packages cannot be imported (a finder refuses them), as in a
venv with ``pip install dynabrain`` alone."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from dynabrain.orchestrator.kernel.extras import EXTRAS

ROOT = Path(__file__).resolve().parents[1]
BLOCKER = f"""
import importlib.abc, sys
class _Missing(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in {sorted(EXTRAS)!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, _Missing())
"""


def slim(code: str, tmp_path: Path) -> subprocess.CompletedProcess:
    script = tmp_path / "slim.py"
    script.write_text(BLOCKER + textwrap.dedent(code), encoding="utf-8")
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_the_base_runs_a_scenario_logs_it_verifies_it_and_imports_the_bridge(tmp_path):
    log = tmp_path / "two_cubes.mcap"
    run = slim(f"""
        import sys
        from dynabrain.orchestrator.cli.main import main
        from dynabrain.bridge import BrainClient  # the remote brain's client
        for argv in (["run", "two_cubes", "--log", {str(log)!r}], ["replay", {str(log)!r}, "--verify"]):
            sys.argv = ["dynabrain", "-q", *argv]
            try:
                main()
            except SystemExit as exc:
                assert exc.code in (0, None), (argv, exc.code)
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in {sorted(EXTRAS)!r})
        print("LOADED", loaded)
        """, tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "LOADED []" in run.stdout and "verify: identical" in run.stdout, run.stdout


@pytest.mark.parametrize(("argv", "extra"), [
    (["run", "fmu_servo"], "fmu"), (["run", "two_cubes_exudyn"], "exudyn"),
    (["view", "--save", "x.rrd", "--no-serve", "x.mcap"], "view"),
])
def test_a_missing_extra_is_refused_by_name(tmp_path, argv, extra):
    run = slim(f"""
        import sys
        from dynabrain.orchestrator.cli.main import main
        sys.argv = ["dynabrain", *{argv!r}]
        main()
        """, tmp_path)
    assert run.returncode != 0 and f"pip install 'dynabrain[{extra}]'" in run.stdout + run.stderr, \
        run.stdout[-2000:] + run.stderr[-2000:]


def test_the_python_api_names_the_extra_too(tmp_path):
    run = slim("""
        from dynabrain.orchestrator import load_world
        from dynabrain.orchestrator.kernel.errors import DynabrainError
        try:
            load_world("fmu_servo")
        except DynabrainError as exc:
            print("REFUSED", exc)
        """, tmp_path)
    assert "REFUSED" in run.stdout and "pip install 'dynabrain[fmu]'" in run.stdout, run.stdout + run.stderr[-2000:]
