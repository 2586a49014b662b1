"""The planner: A* over world states, children evaluated as one batch; the plan it finds, executed on the
world, gives the predicted outcome bit for bit; failures and exhausted budgets are values, bad specs errors.
A* as the books have it: the cheapest plan whatever the order of the actions, a closed set, children of
different lengths in one batch, a child whose worker died run again."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator import Batch, DynabrainError, load_world
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


def to_go(o) -> float:
    """The heuristic, in the cost's unit (seconds): the distance left at 0.5 m/s."""
    return abs(o["core.s.q"] - TARGET) / 0.5


def test_the_plan_found_executes_as_predicted(slider):
    start = slider.export_state()
    plan = search(slider, PUSHES, record=["core.s.q", "core.s.qd"], backend="serial", heuristic=to_go, goal=near)
    assert plan.found and plan.actions and plan.stats.expanded >= 1
    assert plan.stats.generated == plan.stats.batches * len(PUSHES)
    assert plan.trajectory["core.s.q"].shape == (50 * len(plan.actions),)
    assert slider.export_state() == start  # searching changed nothing
    slider.import_state(plan.states[0])
    done = plan.execute(slider)
    assert done["core.s.q"].tobytes() == plan.trajectory["core.s.q"].tobytes()
    assert abs(slider.get("core.s.q") - TARGET) < 0.02


@pytest.fixture(scope="module")
def processes():
    """A slider world and a batch of two worker processes for it, shared by the tests that only read."""
    world = load_world(SLIDER)
    batch = Batch(world, backend="processes", workers=2)
    yield world, batch
    batch.close()
    world.close()


def test_children_on_worker_processes_find_the_same_plan(processes):
    slider, batch = processes
    request = dict(record=["core.s.q", "core.s.qd"], heuristic=to_go, goal=near)
    serial = search(slider, PUSHES, backend="serial", **request)
    spread = search(slider, PUSHES, batch=batch, **request)
    assert [a.name for a in spread.actions] == [a.name for a in serial.actions]
    assert spread.trajectory["core.s.q"].tobytes() == serial.trajectory["core.s.q"].tobytes()


def test_failed_children_cost_infinity_and_the_search_goes_on(slider):
    actions = [*PUSHES, Action("blow up", 50, inputs={"core.s.force": 1e300})]
    plan = search(slider, actions, record=["core.s.q", "core.s.qd"], backend="serial",
                  heuristic=to_go, goal=near, failed=lambda o: o["core.s.q"] < -0.2 and "went the wrong way")
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


QUICK = Action("quick: 40 N for 0.1 s", 50, inputs={"core.s.force": 40.0})
SLOW = Action("slow: 10 N for 0.4 s", 200, inputs={"core.s.force": 10.0})


@pytest.mark.parametrize("backend", ["serial", "processes"])
def test_the_cheapest_of_two_goal_reaching_actions_whatever_their_order(processes, backend):
    """Both actions end past 15 cm (the quick one at 19 cm, the slow one at 62 cm); the plan is the
    quick one (0.1 s, not 0.4 s) in either order, and both children ran in one batch."""
    slider, spread = processes
    with Batch(slider, backend="serial") as serial:
        batch = serial if backend == "serial" else spread
        for actions in ([QUICK, SLOW], [SLOW, QUICK]):
            plan = search(slider, actions, record=["core.s.q"], heuristic=lambda o: 0.0, batch=batch,
                          goal=lambda o: o["core.s.q"] > 0.15)
            assert plan.found and plan.actions == [QUICK], [a.name for a in actions]
            assert plan.cost == pytest.approx(0.1)
            assert (plan.stats.expanded, plan.stats.batches, plan.stats.generated) == (1, 1, 2)
            assert plan.trajectory["core.s.q"].shape == (50,)


def test_the_closed_set_drops_states_seen_and_finds_the_same_cost():
    """Pushes left, right and none, no heuristic (uniform cost): without a closed set the search
    expands every path; with it (the rounded signature, or a coarser key of the user's) fewer."""
    world = load_world(SLIDER)
    try:
        actions = [Action(f"push {f:+g} N", 50, inputs={"core.s.force": f}) for f in (-4.0, 0.0, 4.0)]
        request = dict(record=["core.s.q", "core.s.qd"], heuristic=lambda o: 0.0, backend="serial",
                       goal=lambda o: o["core.s.q"] > 0.12, max_expansions=500)
        tree = search(world, actions, closed=False, **request)
        graph = search(world, actions, **request)
        coarse = search(world, actions, key=lambda o: (round(float(o["core.s.q"]), 2), round(float(o["core.s.qd"]), 1)),
                        **request)
        assert tree.found and graph.found and coarse.found
        assert tree.cost == pytest.approx(graph.cost) and coarse.cost == pytest.approx(graph.cost)
        assert tree.stats.duplicates == 0 < graph.stats.duplicates <= coarse.stats.duplicates
        assert coarse.stats.expanded <= graph.stats.expanded < tree.stats.expanded
        world.import_state(coarse.states[0])
        assert coarse.execute(world)["core.s.q"].tobytes() == coarse.trajectory["core.s.q"].tobytes()
    finally:
        world.close()


def test_children_of_several_nodes_share_a_batch(slider):
    request = dict(record=["core.s.q", "core.s.qd"], heuristic=to_go, goal=near, backend="serial")
    one = search(slider, PUSHES, **request)
    three = search(slider, PUSHES, nodes_per_batch=3, **request)
    assert three.found and three.cost == pytest.approx(one.cost)
    assert three.stats.batches < three.stats.expanded
    assert three.stats.generated == three.stats.expanded * len(PUSHES)


def test_a_child_whose_worker_died_is_run_again_not_pruned(slider):
    """A worker killed while the search runs: the branch it was handed is run again (on its
    replacement), and the search finds what it finds on one process."""
    request = dict(record=["core.s.q", "core.s.qd"], goal=lambda o: False, max_expansions=4)
    serial = search(slider, PUSHES, heuristic=to_go, backend="serial", **request)
    with Batch(slider, backend="processes", workers=2) as batch:
        killed = []

        def heuristic(o):
            if not killed:  # between the first batch and the second
                victim = batch._pool._workers[0].proc
                os.kill(victim.pid, signal.SIGKILL)
                victim.wait()
                killed.append(victim.pid)
            return to_go(o)

        spread = search(slider, PUSHES, heuristic=heuristic, batch=batch, **request)
        assert batch._pool.replaced == 1
    assert spread.stats.retried >= 1 and not spread.stats.failed
    assert spread.stats.expanded == serial.stats.expanded
    assert [a.name for a in spread.actions] == [a.name for a in serial.actions]
    assert spread.trajectory["core.s.q"].tobytes() == serial.trajectory["core.s.q"].tobytes()
