"""The planner: A* over world states, children evaluated as one batch; the plan it finds, executed on the
world, gives the predicted outcome bit for bit; failures and exhausted budgets are values, bad specs errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator import DynabrainError, load_world
from dynabrain.orchestrator.brain.plan import Action, search

SLIDER = Path(__file__).resolve().parent / "scenarios" / "slider.yaml"
TARGET = 0.3
PUSHES = [Action(f"push {f:+g} N", 50, inputs={"core.s.force": f}) for f in (-4.0, -1.0, 0.0, 1.0, 4.0)]


@pytest.fixture
def slider():
    world = load_world(SLIDER)
    yield world
    world.close()


def near(o) -> bool:
    return abs(o["core.s.q"] - TARGET) < 0.02 and abs(o["core.s.qd"]) < 0.1


def test_the_plan_found_executes_as_predicted(slider):
    start = slider.export_state()
    plan = search(slider, PUSHES, record=["core.s.q", "core.s.qd"], backend="serial",
                  heuristic=lambda o: abs(o["core.s.q"] - TARGET), goal=near)
    assert plan.found and plan.actions and plan.stats.expanded >= 1
    assert plan.stats.generated == plan.stats.batches * len(PUSHES)
    assert plan.trajectory["core.s.q"].shape == (50 * len(plan.actions),)
    assert slider.export_state() == start  # searching changed nothing
    slider.import_state(plan.states[0])
    done = plan.execute(slider)
    assert done["core.s.q"].tobytes() == plan.trajectory["core.s.q"].tobytes()
    assert abs(slider.get("core.s.q") - TARGET) < 0.02


def test_children_on_worker_processes_find_the_same_plan(slider):
    request = dict(record=["core.s.q", "core.s.qd"], heuristic=lambda o: abs(o["core.s.q"] - TARGET), goal=near)
    serial = search(slider, PUSHES, backend="serial", **request)
    spread = search(slider, PUSHES, backend="processes", **request)
    assert [a.name for a in spread.actions] == [a.name for a in serial.actions]
    assert spread.trajectory["core.s.q"].tobytes() == serial.trajectory["core.s.q"].tobytes()


def test_failed_children_cost_infinity_and_the_search_goes_on(slider):
    actions = [*PUSHES, Action("blow up", 50, inputs={"core.s.force": 1e300})]
    plan = search(slider, actions, record=["core.s.q", "core.s.qd"], backend="serial",
                  heuristic=lambda o: abs(o["core.s.q"] - TARGET), goal=near,
                  failed=lambda o: o["core.s.q"] < -0.2 and "went the wrong way")
    assert plan.found
    reasons = [reason for _path, reason in plan.stats.failed]
    assert any("core" in r for r in reasons)  # the diverging branch, with the module's message
    assert all("blow up" not in a.name for a in plan.actions)


def test_an_exhausted_budget_returns_the_best_node(slider):
    plan = search(slider, PUSHES, record=["core.s.q"], backend="serial", max_expansions=2,
                  heuristic=lambda o: abs(o["core.s.q"] - TARGET), goal=lambda o: False)
    assert not plan.found and plan.stats.expanded == 2
    assert plan.actions and np.isfinite(plan.node.h)


def test_bad_specs_are_refused_before_anything_runs(slider):
    tick = slider.tick_count
    with pytest.raises(DynabrainError, match=r"core\.s\.forc"):
        search(slider, [Action("x", 10, inputs={"core.s.forc": 1.0})], record=[], heuristic=abs, goal=bool)
    with pytest.raises(DynabrainError, match="positive integer"):
        search(slider, [Action("x", 0, inputs={"core.s.force": 1.0})], record=[], heuristic=abs, goal=bool)
    with pytest.raises(DynabrainError, match="needs"):
        search(slider, [Action("x", 10, inputs={"core.s.force": [1.0, 2.0]})], record=[], heuristic=abs,
               goal=bool)
    with pytest.raises(DynabrainError, match="no signal"):
        search(slider, PUSHES, record=["core.nothing"], heuristic=abs, goal=bool)
    assert slider.tick_count == tick
