"""Scale (issue 17, point 5): a scene above `MAX_BODIES` is refused before a body is made; loading does
each expensive MuJoCo step once and sizes MuJoCo's memory by the scene, not by the square of its degrees
of freedom; a history above its budget is refused at load (a scenario) or at the first tick (a World),
naming the figure; MuJoCo's warnings are logged once per kind and summarised once per run.

The timings are for the report, not asserted: `check` of a 10,000-box grid takes about 16 s (11 s of it
MuJoCo's compiler, quadratic in the free bodies), so it is not run here."""

from __future__ import annotations

import logging
import textwrap

import mujoco
import numpy as np
import pytest
from typer.testing import CliRunner

from dynabrain.modules.mujoco import scene as ms
from dynabrain.modules.mujoco import spec_source as mss
from dynabrain.modules.mujoco import warning_log
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator import Module, Port, World
from dynabrain.orchestrator.cli import main
from dynabrain.orchestrator.kernel.core import BodySpec, SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, ScenarioError
from dynabrain.orchestrator.kernel.history import HistoryBudgetError, format_bytes, parse_bytes
from dynabrain.orchestrator.scenario import limits, model
from dynabrain.orchestrator.scenario.model import load_world


def _scenario(tmp_path, text: str, name: str = "s.yaml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def _grid(nx: int, ny: int, name: str = "b") -> str:
    return (f"  - grid: {{of: {{box: {{name: {name}, size: [0.1, 0.1, 0.1], mass: 0.2, pos: [0, 0, 0.3]}}}}, "
            f"count: [{nx}, {ny}], spacing: [0.2, 0.2]}}\n")


def _problems(path) -> list:
    with pytest.raises(ScenarioError) as caught:
        load_world(path)
    return caught.value.problems


# -- the scene's size ---------------------------------------------------------------------------------
def test_a_scene_above_max_bodies_is_refused_before_a_body_is_made(tmp_path, monkeypatch):
    def parse_scene(*args, **kwargs):
        raise AssertionError("the scene was parsed")

    monkeypatch.setattr(model, "parse_scene", parse_scene)
    path = _scenario(tmp_path, "name: s\nscene:\n  - plane: {name: floor}\n" + _grid(100, 100, "a")
                     + _grid(100, 100, "b"))
    (problem,) = _problems(path)
    assert problem.line == 3 and problem.field == "scene"
    assert "20000 bodies" in problem.message and f"at most {limits.MAX_BODIES} (MAX_BODIES)" in problem.message
    done = CliRunner().invoke(main.app, ["check", str(path)])
    assert done.exit_code == 2 and "MAX_BODIES" in done.output


def test_the_grid_limit_is_the_scene_limit(tmp_path):
    assert limits.MAX_GRID == limits.MAX_BODIES
    path = _scenario(tmp_path, "name: s\nscene:\n  - plane: {name: floor}\n" + _grid(101, 100))
    (problem,) = _problems(path)
    assert problem.line == 4 and "MAX_GRID" in problem.message  # the grid, on its own line
    assert limits.scene_bodies([{"plane": {}}, {"grid": {"count": [100, 100]}}, {"box": {}}]) == 10_001


def test_a_model_file_above_max_bodies_is_refused_before_the_engine_reads_it(tmp_path, monkeypatch):
    def read(*args, **kwargs):
        raise AssertionError("MuJoCo read the model file")

    monkeypatch.setattr(mss, "_spec_from_file", read)
    bodies = "".join(f'<body name="b{i}"><geom size=".1"/></body>' for i in range(limits.MAX_BODIES + 1))
    (tmp_path / "big.xml").write_text(f"<mujoco><worldbody>{bodies}</worldbody></mujoco>")
    path = _scenario(tmp_path, "name: s\nscene: {model: big.xml}\n")
    (problem,) = _problems(path)
    assert problem.field == "scene.model" and f"{limits.MAX_BODIES + 1} bodies" in problem.message


def test_the_mujoco_core_refuses_more_bodies_than_mujoco_simulates(monkeypatch):
    monkeypatch.setattr(mss, "MAX_BODIES", 3)
    boxes = [BodySpec(f"b{i}", "box", (0.1, 0.1, 0.1), pos=(0.0, 0.2 * i, 0.3)) for i in range(4)]
    with pytest.raises(DynabrainError, match=r"4 bodies: MuJoCo simulates at most 3"):
        MujocoCore("core", SceneSpec(bodies=tuple(boxes)))
    MujocoCore("core", SceneSpec(bodies=tuple(boxes[:3]))).close()


# -- the work of loading ----------------------------------------------------------------------------------
def test_a_core_builds_its_spec_once_and_asks_mujoco_for_no_list_of_every_element(monkeypatch):
    built, named, compiled = [], [], []
    spec_from_bodies, name_everything, build = mss._spec_from_bodies, mss._name_everything, ms.build_structure
    monkeypatch.setattr(mss, "_spec_from_bodies", lambda *a: built.append(1) or spec_from_bodies(*a))
    monkeypatch.setattr(mss, "_name_everything", lambda *a: named.append(1) or name_everything(*a))
    monkeypatch.setattr(ms, "build_structure", lambda *a: compiled.append(1) or build(*a))
    boxes = tuple(BodySpec(f"b{i}", "box", (0.1, 0.1, 0.1), pos=(0.2 * i, 0.0, 0.3)) for i in range(20))
    core = MujocoCore("core", SceneSpec(bodies=(BodySpec("floor", "plane", ()), *boxes)))
    assert (len(built), len(named), len(compiled)) == (1, 0, 1)  # (MuJoCo's lists of every geom or joint
    core.make(["b0"])  # cost time quadratic in them; adding a body to a spec walks every body there)
    assert (len(built), len(named), len(compiled)) == (2, 0, 2)  # a new structure: built and compiled again
    core.close()


def test_mujoco_memory_is_sized_by_the_scene():
    boxes = tuple(BodySpec(f"b{i}", "box", (0.1, 0.1, 0.1), mass=0.2, pos=(0.2 * (i % 32), 0.2 * (i // 32), 0.08))
                  for i in range(1024))
    core = MujocoCore("core", SceneSpec(bodies=(BodySpec("floor", "plane", ()), *boxes)))
    m = core.mj.model
    size = mss.ModelSize(nbody=m.nbody - 1, ngeom=m.ngeom, nv=m.nv, neq=m.neq)
    assert m.nv == 6144 and m.narena == mss.arena_bytes(size) < 400 * 2**20  # MuJoCo's own rule: 1.7 GB
    d = core.mj.data
    for _ in range(50):  # every box lands on the floor: 4096 contacts fit
        mujoco.mj_step(m, d)
    assert d.ncon >= 4 * 1024 and d.maxuse_arena < m.narena
    core.close()
    small = MujocoCore("core", SceneSpec(bodies=(BodySpec("floor", "plane", ()), boxes[0])))
    assert small.mj.model.narena < mss.arena_bytes(mss.ModelSize(2, 2, 6, 0))  # MuJoCo's own rule where it gives less
    small.close()


def test_a_model_files_own_memory_is_kept(tmp_path):
    (tmp_path / "m.xml").write_text('<mujoco><size memory="3M"/><worldbody><body name="b"><freejoint/>'
                                    '<geom size=".1"/></body></worldbody></mujoco>')
    core = MujocoCore("core", SceneSpec(model=str(tmp_path / "m.xml")))
    assert core.mj.model.narena == 3 * 2**20
    core.close()


# -- history ------------------------------------------------------------------------------------------------
SMALL = """
    name: s
    world: {step: 2ms, duration: 20ms, core: mujoco, keyframe_every: 1, history: HISTORY}
    scene:
      - plane: {name: floor}
      - box: {name: b, size: [0.1, 0.1, 0.1], mass: 0.2, pos: [0, 0, 0.3]}
"""


def test_a_history_above_the_budget_is_refused_at_load_naming_the_figure(tmp_path):
    path = _scenario(tmp_path, SMALL.replace("HISTORY", "1000000000"))
    (problem,) = _problems(path)
    assert problem.field == "world.history" and problem.line == 3
    assert "1,000,000,000 ticks would hold 1.1 TiB when full" in problem.message
    assert "history budget" in problem.message and "DYNABRAIN_HISTORY_BUDGET" in problem.message
    done = CliRunner().invoke(main.app, ["check", str(path)])
    assert done.exit_code == 2 and "TiB when full" in done.output


def test_the_budget_is_the_scenarios_or_the_environments(tmp_path, monkeypatch):
    tight = _scenario(tmp_path, SMALL.replace("HISTORY", "1000, history_budget: 1MiB"))
    (problem,) = _problems(tight)
    assert "above the history budget of 1.0 MiB (the world's own" in problem.message
    load_world(_scenario(tmp_path, SMALL.replace("HISTORY", "1000, history_budget: 2MiB"), "ok.yaml")).close()
    bad = _scenario(tmp_path, SMALL.replace("HISTORY", "1000, history_budget: lots"), "bad.yaml")
    (problem,) = _problems(bad)
    assert problem.field == "world.history_budget" and "not a size" in problem.message
    monkeypatch.setenv("DYNABRAIN_HISTORY_BUDGET", "1MiB")
    (problem,) = _problems(_scenario(tmp_path, SMALL.replace("HISTORY", "1000"), "env.yaml"))
    assert "DYNABRAIN_HISTORY_BUDGET=1MiB" in problem.message
    load_world(_scenario(tmp_path, SMALL.replace("HISTORY", "100"), "short.yaml")).close()


def test_sizes():
    assert parse_bytes("2GiB") == 2 * 2**30 and parse_bytes("500 MB") == 500 * 10**6 and parse_bytes(4096) == 4096
    assert 0 < parse_bytes("25%") <= parse_bytes("50%")
    for bad in ("0", "-1GB", "2 parsecs", "150%", True, None):
        with pytest.raises(DynabrainError):
            parse_bytes(bad)
    assert format_bytes(1.5 * 2**40) == "1.5 TiB" and format_bytes(512) == "512 B"


class Eye(Module):
    """An image of ``size`` x ``size`` RGB values on the bus, as a camera's."""

    def __init__(self, name: str, size: int = 512):
        super().__init__(name)
        self.size = size

    def outputs(self):
        return (Port("rgb", (self.size, self.size, 3), "1"),)

    def step(self, t_ns, dt_ns):
        pass


def test_a_world_built_in_python_is_refused_at_its_first_tick_and_when_it_grows():
    world = World("w", history=1000, keyframe_every=1)  # a state every tick (the default keeps about half)
    world.history.budget = 2**30
    world.add_module(Eye("eye", 64))  # 98 KiB a state: 96 MiB when full
    world.tick(2)
    world.add_module(Eye("big", 512))  # + 6 MiB a state: 6 GiB when full
    with pytest.raises(HistoryBudgetError, match=r"would hold 6\.\d GiB when full .* above the history budget"):
        world.tick()
    assert world.tick_count == 2  # refused before the tick
    world.remove_module("big")
    world.tick()
    world.close()


def test_a_camera_whose_history_would_not_fit_is_refused(tmp_path):
    from dynabrain.modules.mujoco.offscreen import RendererUnavailableError, open_gl

    try:
        open_gl(8, 8)[1].free()
    except RendererUnavailableError as exc:
        pytest.skip(str(exc))
    (tmp_path / "room.xml").write_text(
        '<mujoco><visual><global offwidth="1024" offheight="1024"/></visual><worldbody>'
        '<geom type="plane" size="1 1 .1"/><camera name="cam" pos="0 -1 1" xyaxes="1 0 0 0 1 1"/>'
        '</worldbody></mujoco>')
    path = _scenario(tmp_path, """
        name: s
        world: {core: mujoco, history: 1000, history_budget: 4GiB}
        scene: {model: room.xml}
        modules:
          - {name: eye, python: dynabrain.modules.camera:Camera, targets: [cam], params: {width: 1024, height: 1024}}
    """)
    (problem,) = _problems(path)  # keyframes every 2 ticks (the default): 502 states kept
    assert problem.field == "world.history"
    assert "would hold 15.7 GiB when full (502 states" in problem.message
    assert "the module 'eye' holds 32.0 MiB" in problem.message
    path.write_text(path.read_text().replace("history: 1000,", "history: 1000, keyframe_every: 1,"))
    (problem,) = _problems(path)  # a state every tick
    assert "would hold 31.3 GiB when full" in problem.message and "the module 'eye' holds 32.0 MiB" in problem.message


# -- MuJoCo's warnings ----------------------------------------------------------------------------------
def test_warnings_are_logged_once_per_kind_and_summarised(caplog):
    warning_log.summary()  # (start counting here)
    with caplog.at_level(logging.DEBUG, logger="dynabrain.mujoco"):
        for i in range(5):
            warning_log.record(f"Nan, Inf or huge value in QACC at DOF {i}. The simulation is unstable. Time = 0.{i}.")
        warning_log.record("Another kind: 1")
    shown = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert [r.getMessage() for r in shown] == [
        "MuJoCo: Nan, Inf or huge value in QACC at DOF 0. The simulation is unstable. Time = 0.0.",
        "MuJoCo: Another kind: 1"]
    line = warning_log.summary()
    assert line.startswith("MuJoCo: 4 more warnings") and "4 x 'Nan, Inf or huge value in QACC at DOF #" in line
    assert warning_log.summary() is None  # counted again from nothing


def test_mujocos_own_warnings_go_through_the_tally():
    assert mujoco.get_mju_user_warning() is warning_log.record
    spec = mujoco.MjSpec()
    body = spec.worldbody.add_body()
    body.add_freejoint()
    body.add_geom(size=[0.1, 0, 0])
    m = spec.compile()
    warning_log.summary()
    for _ in range(3):  # MuJoCo warns once per data: fresh data each time, as recompiles and forks make
        d = mujoco.MjData(m)
        d.qvel[0] = np.nan
        mujoco.mj_step(m, d)
    assert sum(warning_log.counts().values()) >= 3 and len(warning_log.counts()) <= 2
    assert "more warnings" in warning_log.summary()


def test_run_prints_the_summary_once(tmp_path):
    path = _scenario(tmp_path, SMALL.replace("HISTORY", "10"))
    warning_log.summary()
    for i in range(3):
        warning_log.record(f"Nan, Inf or huge value in QVEL at DOF {i}.")
    done = CliRunner().invoke(main.app, ["run", str(path)])
    assert done.exit_code == 0, done.output
    assert done.output.count("2 more warnings of the kinds shown above") == 1
    assert warning_log.summary() is None

