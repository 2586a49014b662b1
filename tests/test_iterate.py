"""Strong coupling (issue 28, item 3): a loop of feedthrough modules declared ``iterate`` is stepped
again from its saved states until its values agree. Real FMUs built from ``fmus/affine`` (y = gain * u
+ offset, direct feedthrough); Python modules for the same loop in code and in a scenario."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator import Module, Param, Port, load_world
from dynabrain.orchestrator.fmu import make_fmu_module
from dynabrain.orchestrator.fmu.build import build_fmu
from dynabrain.orchestrator.kernel.errors import AlgebraicLoopError, WiringError
from dynabrain.orchestrator.kernel.iterate import LoopNotConvergedError
from dynabrain.orchestrator.kernel.world import World

FMUS = Path(__file__).resolve().parents[1] / "fmus"

pytestmark = pytest.mark.usefixtures("fmu_cache")


@pytest.fixture(scope="module", params=[2, 3], ids=["fmi2", "fmi3"])
def affine(request) -> Path:
    return build_fmu(FMUS / "affine", request.param)


def fmu_loop(ref: Path, gains: tuple[float, float], offsets: tuple[float, float], *, compiled: bool = True,
             **loop) -> World:
    world = World("loop", step="1ms", history=50, compiled=compiled)
    for name, gain, offset in zip("ab", gains, offsets, strict=True):
        world.add_module(make_fmu_module(name, str(ref), base_dir=".", params={"gain": gain, "offset": offset},
                                         targets=[]))
    world.iterate(["a", "b"], name="ab", **loop)
    world.connect("a.y", "b.u")
    world.connect("b.y", "a.u")
    return world


def test_an_fmu_loop_is_refused_unless_declared(affine):
    world = World("loop", step="1ms")
    for name in "ab":
        world.add_module(make_fmu_module(name, str(affine), base_dir=".", params={}, targets=[]))
    world.connect("a.y", "b.u")
    with pytest.raises(AlgebraicLoopError):
        world.connect("b.y", "a.u")


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "plain"])
def test_a_contracting_fmu_loop_agrees_at_the_analytic_fixed_point(affine, compiled):
    # y_a = 0.5 y_b + 1, y_b = -0.25 y_a + 2: y_a = 16/9, y_b = 14/9
    world = fmu_loop(affine, (0.5, -0.25), (1.0, 2.0), compiled=compiled, tolerance=1e-12)
    world.tick(5)
    assert world.get("a.y") == pytest.approx(16 / 9, abs=1e-11)
    assert world.get("b.y") == pytest.approx(14 / 9, abs=1e-11)
    report = world.loop_report("ab")
    assert report.converged and report.residual <= 1e-11
    assert report.iterations <= 2  # warm started from the tick before
    assert world.get("a.steps") == 5 and world.get("b.steps") == 5  # the runs taken again were rolled back


def test_a_loop_that_does_not_contract_is_solved_by_broyden(affine):
    # y_a = 2 y_b + 1, y_b = y_a: the fixed point x = g(x) runs away; y_a = -1 solves it
    world = fmu_loop(affine, (2.0, 1.0), (1.0, 0.0), tolerance=1e-12)
    world.tick()
    assert world.get("a.y") == pytest.approx(-1.0, abs=1e-10)
    assert world.get("b.y") == pytest.approx(-1.0, abs=1e-10)
    assert world.loop_report("ab").converged
    world.tick(3)
    assert world.get("a.steps") == 4


def test_a_loop_with_no_solution_fails_at_its_tick_and_rolls_back(affine):
    # y_a = y_b + 1, y_b = y_a: no values agree
    world = fmu_loop(affine, (1.0, 1.0), (1.0, 0.0), max_iterations=8)
    world.set("a.offset", 0.0)  # first a loop that agrees (y = 0)
    world.tick(3)
    before = world.bus.copy()
    world.set("a.offset", 1.0)
    events = []
    world.observe(type("Events", (), {"on_event": lambda self, view, e: events.append(e),
                                      "on_tick": lambda self, view: None,
                                      "on_rollback": lambda self, view, n: None,
                                      "on_imagined": lambda self, view, i: None,
                                      "on_close": lambda self, view: None})())
    with pytest.raises(LoopNotConvergedError) as caught:
        world.tick()
    assert caught.value.tick == 3 and caught.value.module == "ab"
    assert "8 iterations" in str(caught.value) and "a.u" in str(caught.value)
    assert world.tick_count == 3 and world.get("a.steps") == 3 and world.get("b.steps") == 3
    assert np.array_equal(world.bus, before)
    report = world.loop_report("ab")
    assert not report.converged and report.iterations == 8
    assert any(e.kind == "iterate" and not e.detail["converged"] for e in events)
    world.set("a.offset", 0.0)  # the world goes on from the tick it was rolled back to
    world.tick()
    assert world.tick_count == 4 and world.get("a.steps") == 4


def test_backtick_and_fork_replay_the_iterated_loop(affine):
    world = fmu_loop(affine, (0.5, -0.25), (1.0, 2.0))
    world.tick(4)
    other = world.fork()
    world.backtick(2)
    world.tick(2)
    other.tick(1)
    world.tick(1)
    assert np.array_equal(world.bus, other.bus)
    assert world.tick_count == other.tick_count == 5 and world.get("a.steps") == 5


class Affine(Module):
    """y = gain * u^3 + offset (nonlinear, feedthrough), with a step count as state."""

    PARAMS = (Param("gain", 1.0), Param("offset", 0.0))

    def __init__(self, name, **kw):
        super().__init__(name, **kw)
        self.steps = 0

    def inputs(self):
        return (Port("u", ()),)

    def outputs(self):
        return (Port("y", ()),)

    def step(self, t_ns, dt_ns):
        self.out["y"][...] = self.params["gain"] * float(self.inp["u"]) ** 3 + self.params["offset"]
        self.steps += 1

    def get_state(self):
        return self.steps

    def set_state(self, state):
        self.steps = state


def test_a_python_module_loop_with_a_nonlinear_member():
    # y_a = u_a^3 + 0.5, y_b = -0.5 u_b^3: y_a = (-0.5 y_a^3)^3 + 0.5, a root the iteration finds
    world = World("py", step="1ms")
    world.add_module(Affine("a", gain=1.0, offset=0.5))
    world.add_module(Affine("b", gain=-0.5))
    world.iterate(["a", "b"], tolerance=1e-12)
    world.connect("a.y", "b.u")
    world.connect("b.y", "a.u")
    world.tick(3)
    a = world.get("a.y")
    assert a == pytest.approx((-0.5 * a ** 3) ** 3 + 0.5, abs=1e-10)
    assert world.get("b.y") == pytest.approx(-0.5 * a ** 3, abs=1e-12)
    assert world.modules["a"].steps == 3
    assert world.loop_report("loop_a_b").converged


def test_a_lockstep_batch_runs_a_looping_world_branch_by_branch():
    from dynabrain.orchestrator import Batch

    world = World("py", step="1ms")
    world.add_module(Affine("a", gain=1.0, offset=0.5))
    world.add_module(Affine("b", gain=-0.5))
    world.iterate(["a", "b"], tolerance=1e-12)
    world.connect("a.y", "b.u")
    world.connect("b.y", "a.u")
    assert world.loops() == ("loop_a_b",)
    try:
        results = {}
        for backend in ("serial", "lockstep"):
            with Batch(world, backend=backend) as batch:
                starts = [world.export_state()] * 2
                results[backend] = batch.run([3, 5], starts=starts, record=["a.y"])
        assert results["lockstep"].signals["a.y"].tobytes() == results["serial"].signals["a.y"].tobytes()
        assert any("iterates a loop" in note for note in results["lockstep"].notes)
    finally:
        world.close()


def test_loop_declarations_are_checked():
    world = World("py", step="1ms")
    world.add_module(Affine("a"))
    with pytest.raises(WiringError, match="no module 'c'"):
        world.iterate(["a", "c"])
    with pytest.raises(WiringError, match="tolerance"):
        world.iterate(["a"], tolerance=0)


def test_a_scenario_declares_a_loop(tmp_path):
    (tmp_path / "loop.yaml").write_text(textwrap.dedent("""
        name: loop
        world: {step: 1ms, duration: 5ms, core: null}
        modules:
          - {name: a, python: "test_iterate:Affine", params: {}}
          - {name: b, python: "test_iterate:Affine", params: {}}
        iterate:
          - {name: ab, modules: [a, b], tolerance: 1.0e-12, max_iterations: 30}
        connect:
          - [a.y, b.u]
          - [b.y, a.u]
    """))
    world = load_world(tmp_path / "loop.yaml", allow_python=["test_iterate"])
    world.tick(2)
    assert world.loop_report("ab").converged
