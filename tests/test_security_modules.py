"""Issue 24, item 1: a class path that a scenario, a log or a bridge call names is allowed or refused
before anything is imported (`kernel.plugins.ClassPolicy`), so no module's top-level code runs unasked.

The trap is a real package on ``sys.path`` whose modules write a file when imported: after each refusal
the file must not exist.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynabrain.bridge import BrainClient, WorldRefusedError
from dynabrain.bridge import protocol as p
from dynabrain.bridge.calls import WorldService
from dynabrain.bridge.testing import ServerProcess
from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.kernel import plugins
from dynabrain.orchestrator.kernel.errors import DynabrainError, ScenarioError
from dynabrain.orchestrator.kernel.module import Module, Port
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.scan import LogError
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.scenario.model import load_scenario, load_world

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()

TRAP = "open({marker!r}, 'a').write('{name} ran\\n')\n"
SCENARIO = """\
name: trap
world: {{step: 2ms, duration: 10ms, core: null}}
modules:
  - {{name: k, python: "{python}"}}
"""


@pytest.fixture()
def trap(tmp_path, monkeypatch):
    """``trap_pkg`` (its ``__main__`` and ``boom`` write ``marker`` when imported) importable from
    ``sys.path``; returns the marker's path."""
    site = tmp_path / "site"
    pkg = site / "trap_pkg"
    pkg.mkdir(parents=True)
    marker = tmp_path / "ran.txt"
    (pkg / "__init__.py").write_text("")
    for name in ("__main__", "boom"):
        (pkg / f"{name}.py").write_text(TRAP.format(marker=str(marker), name=name) + "class X:\n    pass\n")
    monkeypatch.syspath_prepend(str(site))
    yield marker
    for name in ("trap_pkg", "trap_pkg.__main__", "trap_pkg.boom"):
        sys.modules.pop(name, None)


def scenario(folder: Path, python: str) -> Path:
    folder.mkdir(exist_ok=True)
    path = folder / "s.yaml"
    path.write_text(SCENARIO.format(python=python))
    return path


@pytest.mark.parametrize("python", ["trap_pkg.__main__:X", "trap_pkg.boom:X", "dynabrain.orchestrator.cli.__main__:X",
                                   "subprocess:Popen", "antigravity:X"])
def test_check_refuses_an_unregistered_class_without_importing_it(trap, tmp_path, python):
    result = runner.invoke(app, ["check", str(scenario(tmp_path / "sc", python))])
    assert result.exit_code == 2, result.output
    text = " ".join(result.output.split())
    assert "s.yaml:4 [modules[0].python]" in text, text
    package = python.split(":")[0].split(".")[0]
    assert ("__main__ module" in text) if "__main__" in python else (f"--allow-python {package}" in text)
    assert not trap.exists()
    assert "antigravity" not in sys.modules


def test_an_allowed_package_is_imported_but_its_main_never(trap, tmp_path):
    path = scenario(tmp_path / "sc", "trap_pkg.boom:X")
    result = runner.invoke(app, ["check", str(path), "--allow-python", "trap_pkg"])
    assert result.exit_code == 2 and "is not a Module subclass" in " ".join(result.output.split())
    assert trap.read_text() == "boom ran\n"
    main = scenario(tmp_path / "sc2", "trap_pkg.__main__:X")
    result = runner.invoke(app, ["check", str(main), "--allow-python", "trap_pkg", "--allow-python", "*"])
    assert result.exit_code == 2 and "__main__ module" in " ".join(result.output.split())
    assert trap.read_text() == "boom ran\n"


LOCAL = """\
from dynabrain.orchestrator import Module, Port


class Local(Module):
    def outputs(self):
        return (Port("y", ()),)

    def step(self, t_ns, dt_ns):
        self.out["y"][...] = 1.0
"""


def test_a_scenario_folders_own_module_is_allowed(tmp_path):
    folder = tmp_path / "mine"
    path = scenario(folder, "sec_local_mod:Local")
    (folder / "sec_local_mod.py").write_text(LOCAL)
    try:
        world = load_world(path)
        world.tick(2)
        assert world.get("k.y") == 1.0
        world.close()
    finally:
        sys.modules.pop("sec_local_mod", None)


def test_an_entry_point_registers_a_class(trap, tmp_path, monkeypatch):
    """A package that declares ``dynabrain.modules`` entry points (a real dist-info on sys.path)."""
    dist = tmp_path / "site" / "trap_pkg-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: trap_pkg\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[dynabrain.modules]\nboom = trap_pkg.boom:X\n")
    plugins.registered.cache_clear()
    try:
        assert "trap_pkg.boom:X" in plugins.registered()
        policy = plugins.ClassPolicy()
        assert policy.refusal("trap_pkg.boom:X") is None
        assert "not allowed" in policy.refusal("trap_pkg.boom:Y")
        with pytest.raises(DynabrainError, match="not a Module subclass"):
            plugins.resolve_module_class("trap_pkg.boom:X", policy)
        assert trap.read_text() == "boom ran\n"
    finally:
        plugins.registered.cache_clear()


def test_importing_the_cli_main_module_runs_nothing():
    done = subprocess.run([sys.executable, "-c", "import dynabrain.orchestrator.cli.__main__"], capture_output=True,
                          text=True, timeout=60, cwd=ROOT)
    assert done.returncode == 0 and done.stdout == "" and "Usage" not in done.stderr, done.stderr


def test_a_bridge_call_cannot_import_the_cli_or_any_other_module(trap):
    world = load_world(ROOT / "bridge" / "arm.yaml")
    try:
        service = WorldService(world, instance=7)
        for python in ("dynabrain.orchestrator.cli.__main__:main", "trap_pkg.boom:X", "os:system"):
            with pytest.raises(DynabrainError, match="not allowed on this server") as err:
                service.make_module(p.ModuleSpec(name="x", python=python))
            assert "add_module 'x'" in str(err.value)
        assert not trap.exists()
        assert service.make_module(p.ModuleSpec(name="c", python="dynabrain.modules.basic:Counter")).name == "c"
        allowed = WorldService(world, instance=8, allow_python=["trap_pkg"])
        with pytest.raises(DynabrainError, match="not a Module subclass"):
            allowed.make_module(p.ModuleSpec(name="x", python="trap_pkg.boom:X"))
    finally:
        world.close()


def test_a_served_world_refuses_the_cli_and_answers_on():
    """The issue's attack, for real: one add_module of the command line's __main__ ran it inside the server,
    which then answered no call. Now it is refused, and the server goes on."""
    with ServerProcess(str(ROOT / "bridge" / "arm.yaml")) as server, \
            BrainClient("arm", connect=server.endpoint, timeout=20) as brain:
        for python in ("dynabrain.orchestrator.cli.__main__:main", "dynabrain.orchestrator.cli.main:app"):
            with pytest.raises(WorldRefusedError, match="not allowed"):
                brain.add_module(name="x", python=python)
        assert brain.status()["tick"] >= 0
        brain.add_module(name="c", python="dynabrain.modules.basic:Counter")
        assert brain.tick() >= 1
    assert "Traceback" not in server.output and "Usage" not in server.output, server.output


class Disguised(Module):
    """A module whose recorded spec names the trap: what a doctored log would say."""

    def outputs(self):
        return (Port("y", ()),)

    def step(self, t_ns, dt_ns):
        self.out["y"][...] = 0.0

    def scenario_spec(self):
        return {"name": self.name, "python": "trap_pkg.boom:X"}


def test_verify_makes_a_logs_modules_under_the_scenario_rules(trap, tmp_path):
    sc = load_scenario(ROOT / "scenarios" / "two_cubes.yaml")
    world = sc.build()
    log = tmp_path / "run.mcap"
    McapLogger(log, window=0).attach(world, sc)
    world.tick(3)
    world.add_module(Disguised("d"))
    world.tick(3)
    world.close()
    with pytest.raises(LogError, match=r"'trap_pkg.boom:X' is not allowed.*--allow-python trap_pkg"):
        verify(log)
    assert not trap.exists()
    result = runner.invoke(app, ["replay", str(log), "--verify"])
    assert result.exit_code == 2 and "--allow-python trap_pkg" in " ".join(result.output.split())
    assert not trap.exists()


LOGGED = """\
name: logged
world: {step: 2ms, duration: 20ms, core: null}
modules:
  - {name: k, python: "sec_log_local:Local"}
"""


def test_a_logs_local_module_is_made_only_where_its_scenario_still_is(tmp_path):
    """A log names the folder of its scenario; that folder's modules count as the scenario's own only while
    the scenario file is there, as recorded (else a log could make any folder's modules "local")."""
    folder = tmp_path / "mine"
    folder.mkdir()
    marker = tmp_path / "imported.txt"
    (folder / "sec_log_local.py").write_text(TRAP.format(marker=str(marker), name="local") + LOCAL)
    (folder / "s.yaml").write_text(LOGGED)
    try:
        sc = load_scenario(folder / "s.yaml")
        world = sc.build()
        McapLogger(tmp_path / "run.mcap", window=0).attach(world, sc)
        world.tick(5)
        world.close()
        sys.modules.pop("sec_log_local", None)
        assert verify(tmp_path / "run.mcap").ok and marker.read_text() == "local ran\nlocal ran\n"
        sys.modules.pop("sec_log_local", None)
        (folder / "s.yaml").write_text(LOGGED + "# changed since\n")
        with pytest.raises(ScenarioError, match=r"'sec_log_local:Local' is not allowed"):
            verify(tmp_path / "run.mcap")
        assert marker.read_text() == "local ran\nlocal ran\n"
    finally:
        sys.modules.pop("sec_log_local", None)
