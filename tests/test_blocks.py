"""The paper's block-moving task (examples/blocks_planner.py): the planner finds the dynamic plan,
and the plan executed on the world gives the predicted outcome bit for bit and reaches the goal."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import blocks_planner as bp

from dynabrain.orchestrator import load_world


def test_the_simulating_planner_pulls_the_base_out_and_the_plan_executes_as_predicted():
    world = load_world(bp.SCENARIO)
    try:
        world.tick(50)
        plan = bp.plan(world, ("slow", "fast"), backend="serial", max_expansions=20)
        assert plan.found, [a.name for a in plan.actions]
        assert any(a.name.endswith("fast") for a in plan.actions)  # the rough, human-like move
        assert len(plan.actions) <= 3
        world.import_state(plan.states[0])
        done = plan.execute(world)
        for name in bp.RECORD:
            assert done[name].tobytes() == plan.trajectory[name].tobytes()
        pos = {b: world.get(f"core.{b}.pos") for b in bp.BLOCKS}
        assert np.linalg.norm(pos["base"][:2] - bp.TARGET) < 0.05
        assert bp.blocks_on("base", pos) == 0
        assert min(p[2] for p in pos.values()) > bp.TABLE_TOP  # every block still on the table
    finally:
        world.close()


def test_the_careful_rule_refuses_moving_a_block_with_blocks_on_it():
    world = load_world(bp.SCENARIO)
    try:
        world.tick(50)
        plan = bp.plan(world, ("slow",), careful=True, backend="serial", max_expansions=1)
        reasons = {reason for _path, reason in plan.stats.failed}
        assert "moved base with blocks on it" in reasons and "moved mid with blocks on it" in reasons
        assert all(not a.name.startswith(("base", "mid")) for a in plan.actions)
    finally:
        world.close()


def test_the_plan_executed_over_the_bridge_ends_where_predicted():
    """The plan sent a tick at a time to the blocks world served over Zenoh (loopback) ends bit for bit
    where the brain predicted."""
    from dynabrain.bridge.testing import ServerProcess

    world = load_world(bp.SCENARIO)
    try:
        world.tick(bp.SETTLE)
        plan = bp.plan(world, ("slow", "fast"), backend="serial", max_expansions=20)
        assert plan.found
        with ServerProcess(str(bp.SCENARIO)) as server:
            remote = bp.execute_remote(plan, server.endpoint, bp.SETTLE)
        for b in bp.BLOCKS:
            assert remote[b].tobytes() == plan.trajectory[f"core.{b}.pos"][-1].tobytes()
    finally:
        world.close()
