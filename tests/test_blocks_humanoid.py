"""The block task done by the humanoid (examples/blocks_humanoid.py, issue 23): the kid's eyes recognise
the stack, the brain adds what it saw to its own world, plans hand pushes by simulating them, and the
plan executed there ends as predicted, bit for bit; streamed as robot commands to a served world with
a robot emulator, it ends within a stated tolerance of the prediction. Faults: an IK target out of
reach is a failed child with its reason; recognised blocks that overlap or float are a clear error;
the robot link lost during execution stops the brain at a named tick."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import blocks_humanoid as bh
import humanoid_eyes as he
import recognised_blocks as rb

from dynabrain.modules.mujoco.offscreen import RendererUnavailableError
from dynabrain.orchestrator import load_world

SMALL = {"movers": ["blue"], "directions": ("left", "right")}
"""A small instance: the blue block pushed left or right, slowly or fast (4 actions)."""
REMOTE_TOLERANCE_M = 0.02
"""The pushed block on the served world ends within this of where the brain predicted (the real blocks
are not exactly the recognised ones). The blocks a
fast push throws off the stack land where chance puts them: for those, on the table and off the blue
block is what the test asks."""


@pytest.fixture(scope="module")
def seen():
    """What the kid's eyes recognise (its blocks), and the scene's true blocks to compare."""
    scene = load_world(bh.SCENARIO)
    try:
        try:
            blocks = bh.look(scene)
        except RendererUnavailableError as exc:
            pytest.skip(f"no offscreen renderer: {exc}")
        return blocks, {b.colour: rb.truth(scene, b.colour) for b in blocks}
    finally:
        scene.close()


@pytest.fixture(scope="module")
def planned(seen):
    world = bh.brain_world(seen[0])
    try:
        plan = bh.plan(world, [b.colour for b in seen[0]], backend="serial", max_expansions=6, **SMALL)
        yield world, plan
    finally:
        world.close()


def test_the_eyes_recognise_the_stacked_blocks(seen):
    blocks, truth = seen
    assert sorted(b.colour for b in blocks) == ["blue", "green", "red"]
    for b in blocks:
        t = truth[b.colour]
        assert np.abs(np.subtract(b.pos, t.pos)).max() < 0.003, (b, t)
        assert np.abs(np.subtract(b.size, t.size)).max() < 0.004, (b, t)


def test_a_small_plan_is_found_and_executes_as_predicted_bit_for_bit(planned):
    world, plan = planned
    assert plan.found, bh.describe("small", plan)
    assert 1 <= len(plan.actions) <= 3
    assert bh.execute(world, plan)  # every recorded signal, bit for bit
    pos = {b: world.get(f"core.{b}.pos") for b in ("blue", "green", "red")}
    assert np.linalg.norm(pos["blue"][:2] - bh.TARGET) < bh.GOAL_M and bh.blocks_on("blue", pos) == 0
    assert world.get("core.pelvis.pos")[2] > bh.FALLEN_Z


def test_an_unreachable_block_is_a_failed_child_with_its_reason_and_the_search_goes_on(seen):
    far = rb.Block("green", (0.04, 0.04, 0.03), (0.42, 0.2, bh.TABLE_TOP_M + 0.015), 0.0)
    world = bh.brain_world([far])
    try:
        plan = bh.plan(world, ["green"], backend="serial", max_expansions=1, speeds=("slow",))
        assert not plan.found and plan.stats.expanded == 1
        assert plan.stats.failed == [(f"green {d} slow", "IK: the hand cannot reach the above keyframe")
                                     for d in ("left", "right")]
        assert world.get("core.green.pos")[0] == pytest.approx(0.42, abs=0.005)  # the world itself untouched
    finally:
        world.close()


def test_recognised_blocks_that_overlap_or_float_are_named():
    def face(colour, top, centre, size=(0.05, 0.05)):
        return he.Face(colour, top, centre, size, 0.0, 100, 50.0)

    with pytest.raises(he.SceneError, match="'red' floats"):
        he.blocks([face("blue", 0.3, (0.16, 0.0)), face("red", 0.5, (0.4, 0.2))], bh.TABLE_TOP_M)
    with pytest.raises(he.SceneError, match="'blue' and 'green' overlap"):
        he.blocks([face("blue", 0.28, (0.16, 0.0)), face("green", 0.285, (0.18, 0.01))], bh.TABLE_TOP_M)


@pytest.fixture()
def served():
    """The "real" world (blocks_humanoid.yaml at t=0) served on loopback with the robot rig ``kid`` and a
    robot emulator on its link."""
    from dynabrain.bridge.testing import EmulatorProcess, ServerProcess

    with ServerProcess(str(bh.SCENARIO), "--robot", f"{bh.ROBOT}=servo", "--deadline", "2s") as server:
        robot = EmulatorProcess(str(bh.SCENARIO), "blocks_humanoid", server.endpoint, "--robot", bh.ROBOT)
        with robot:
            yield server, robot


def test_the_plan_streamed_to_a_served_world_with_the_robot_ends_near_the_prediction(planned, served):
    world, plan = planned
    names = ["blue", "green", "red"]
    real = bh.execute_remote(world, plan, names, served[0].endpoint)
    predicted = plan.trajectory["core.blue.pos"][-1]
    assert np.linalg.norm(real["blue"] - predicted) < REMOTE_TOLERANCE_M, (real, predicted)
    assert np.linalg.norm(real["blue"][:2] - bh.TARGET) < bh.GOAL_M and bh.blocks_on("blue", real) == 0, real
    assert min(p[2] for p in real.values()) > bh.TABLE_TOP_M, real


def test_losing_the_robot_link_during_execution_stops_the_brain_at_a_named_tick(planned, served):
    from dynabrain.bridge.errors import RobotLostError

    world, plan = planned
    robot = served[1]

    def pull_the_cable(tick: int) -> None:  # the robot goes away while the plan plays
        if tick >= bh.PLAN_AT + 100 and robot.alive():
            robot.kill()
            time.sleep(0.5)  # the link notices the closed connection

    with pytest.raises(RobotLostError, match=r"the robot link was lost at tick \d+") as lost:
        bh.execute_remote(world, plan, ["blue"], served[0].endpoint, ticked=pull_the_cable)
    assert bh.PLAN_AT + 100 <= lost.value.tick <= bh.PLAN_AT + 200, lost.value
