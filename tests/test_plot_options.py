"""``dynabrain plot`` on a brain's log (issue 29, item 4): a brain that sets an input every tick makes one
band, not a line per edit; --events picks the kinds; --imagined overlays the futures the brain kept (their
values as the batch recorded them); the expectation results (one passed, one failed) are read for the
strip; --split, and components whose scales differ, get a panel each. Real MuJoCo, real MCAP files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator import Batch
from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.plot import PlotOptions, _futures, panels, plot, resolve
from dynabrain.orchestrator.logs.plot_marks import BAND_MIN, bands, event_marks, results
from dynabrain.orchestrator.logs.read import read_index
from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

SLIDER = Path(__file__).resolve().parent / "scenarios" / "slider.yaml"
DT_S = 0.002


@pytest.fixture(scope="module")
def brain_log(tmp_path_factory):
    """A brain pushing the slider's cart with a force it sets every tick for 100 ticks, one parameter-like
    edit apart, then a batch of three pushes, two kept as imagined futures."""
    path = tmp_path_factory.mktemp("plot") / "brain.mcap"
    sc = load_scenario(SLIDER)
    world = sc.build()
    McapLogger(path).attach(world, sc)
    for k in range(100):
        world.set("core.s.force", 1.0 + 0.01 * k)
        world.tick(1)
    world.tick(20)
    with Batch(world, backend="serial") as batch:
        forces = np.array([np.full(30, f) for f in (-3.0, 0.0, 3.0)])
        pushes = batch.run(30, branches=3, inputs={"core.s.force": forces}, record=["core.cart.pos", "core.s.q"])
        pushes.imagine(world, "push", branches=[0, 2])
    world.tick(40)
    world.close()
    return path, pushes


@pytest.fixture(scope="module")
def scenario_log(tmp_path_factory):
    """The slider run as a scenario with two expectations, one failing."""
    tmp = tmp_path_factory.mktemp("expect")
    text = SLIDER.read_text().replace("duration: 2s", "duration: 0.1s")
    (tmp / "slider.yaml").write_text(text + "expect:\n"
                                     "  - {at: 0.05s, that: 'cart.z > 0.01', name: the cart stands}\n"
                                     "  - {during: [0s, 0.1s], that: 'cart.z > 1', name: the cart flies}\n")
    sc = load_scenario(tmp / "slider.yaml")
    world = sc.build()
    logger = McapLogger(tmp / "run.mcap").attach(world, sc)
    result = run_scenario(sc, world)
    logger.log_result(result)
    logger.close()
    return tmp / "run.mcap"


def test_an_input_set_every_tick_is_one_band(brain_log):
    path, _pushes = brain_log
    index = read_index(path)
    marks = event_marks(index.events, None)
    found, single = bands(marks, DT_S)
    assert [(b.kind, b.count, b.names) for b in found] == [("set", 100, ("core.s.force",))]
    assert found[0].label == "set x100: core.s.force"
    assert found[0].end_s - found[0].start_s == pytest.approx(99 * DT_S)
    assert all(m.kind != "set" for m in single)
    assert event_marks(index.events, []) == []  # --events none
    assert {m.kind for m in event_marks(index.events, ["imagined"])} == {"imagined"}
    few = [m for m in marks if m.kind == "set"][:BAND_MIN - 1]  # too few for a band: lines
    assert bands(few, DT_S) == ([], few)


def test_imagined_futures_are_the_values_the_batch_recorded(brain_log):
    path, pushes = brain_log
    index = read_index(path)
    q = resolve(index, "s.q")
    futures = _futures(index, [q, resolve(index, "cart.pos[x]")])
    assert sorted(f.label for f in futures) == ["push/0", "push/2"]
    for f in futures:
        branch = int(f.label.split("/")[1])
        assert np.array_equal(f.values[0][:, 0], np.asarray(pushes.signals["core.s.q"][branch]).reshape(-1))
        assert f.values[1].shape == (30, 1)
        assert np.allclose(np.diff(f.times), DT_S)


def test_expectation_results_and_panels(scenario_log, brain_log):
    found = results(read_index(scenario_log).events, DT_S)
    assert [(r.label, r.passed) for r in found] == [("the cart stands", True), ("the cart flies", False)]
    assert found[1].start_s == 0.0 and found[1].end_s == pytest.approx(0.1)
    flat = np.column_stack([np.linspace(0, 1, 50), np.linspace(0, 1e-4, 50), np.full(50, 0.05)])
    assert [p.columns for p in panels([flat], split=False)] == [(0,), (1,), (2,)]  # scales differ
    same = np.column_stack([np.linspace(0, 1, 50), np.linspace(0, -2, 50)])
    assert [p.columns for p in panels([same], split=False)] == [(0, 1)]
    assert [p.columns for p in panels([same], split=True)] == [(0,), (1,)]
    one_moves = np.column_stack([np.linspace(0, 1, 50), np.zeros(50), np.full(50, 0.05)])
    assert [p.columns for p in panels([one_moves], split=False)] == [(0, 1, 2)]


def test_the_cli_draws_them(brain_log, scenario_log, tmp_path):
    path, _pushes = brain_log
    runner = CliRunner()
    got = runner.invoke(app, ["plot", str(path), "cart.pos", "s.q", "--imagined", "--events", "set,imagined",
                              "-o", str(tmp_path / "brain.png")])
    assert got.exit_code == 0, got.output
    assert (tmp_path / "brain.png").stat().st_size > 10_000
    got = runner.invoke(app, ["plot", str(scenario_log), "cart.pos", "--split", "-o", str(tmp_path / "run.png")])
    assert got.exit_code == 0, got.output
    out = plot(scenario_log, ["cart.pos[z]"], tmp_path / "bare.png", PlotOptions(events=(), expectations=False))
    assert Path(out).exists()
