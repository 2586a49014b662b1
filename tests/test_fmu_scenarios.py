"""Scenarios mixing FMU modules and the MuJoCo core: expectations hold, rollback across FMU and
physics state is bit-exact, a fork predicts the world, isolation in a scenario changes no bit."""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario import load_world
from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"


pytestmark = pytest.mark.usefixtures("fmu_cache")  # FMUs built here go to a cache of this module's own


@pytest.mark.parametrize("name", ["fmu_moving_floor", "fmu_servo"])
def test_fmu_scenario_expectations_hold(name):
    result = run_scenario(load_scenario(SCENARIOS / f"{name}.yaml"))
    failed = [f"{e.label}: {e.detail}" for e in result.expectations if not e.passed]
    assert result.error is None and not failed, failed
    assert len(result.expectations) >= 3


def states_bytes(world: World) -> bytes:
    """Every module's state (FMU states pickle as their serialized bytes), for exact comparison."""
    return pickle.dumps([(name, m.get_state()) for name, m in world.modules.items()])


def test_rollback_across_fmu_and_physics_is_bit_exact():
    world = load_world(SCENARIOS / "fmu_moving_floor.yaml")
    try:
        world.tick(950)
        buses, states = [], []
        for _ in range(100):  # across the event at 2 s (tick 1000) that switches the drive off
            world.tick()
            buses.append(world.snapshot().bus)
            states.append(states_bytes(world))
        assert world.get("floor.enabled") is False
        world.backtick(100)
        assert world.get("floor.enabled") is True
        for bus, state in zip(buses, states, strict=True):
            world.tick()
            assert world.snapshot().bus.tobytes() == bus.tobytes()
            assert states_bytes(world) == state
    finally:
        world.close()


def test_fork_predicts_the_world_with_fmus():
    world = load_world(SCENARIOS / "fmu_servo.yaml")
    try:
        world.tick(300)
        plan = world.fork()
        try:
            plan.tick(500)  # past the 1.5 s event
            world.tick(500)
            assert plan.snapshot().bus.tobytes() == world.snapshot().bus.tobytes()
            assert states_bytes(plan) == states_bytes(world)
        finally:
            plan.close()
    finally:
        world.close()


def test_isolate_in_a_scenario_changes_no_bit(tmp_path):
    text = (SCENARIOS / "fmu_servo.yaml").read_text()
    isolated = tmp_path / "isolated.yaml"
    fmus = SCENARIOS.parent / "fmus"
    isolated.write_text(text.replace("fmu: fmus/servo,", f"fmu: {fmus}/servo, isolate: true,"))
    assert "isolate: true" in isolated.read_text()
    plain = load_world(SCENARIOS / "fmu_servo.yaml")
    other = load_world(isolated)
    try:
        assert other.modules["servo"].pid is not None
        for world in (plain, other):
            world.tick(200)
        assert plain.snapshot().bus.tobytes() == other.snapshot().bus.tobytes()
    finally:
        plain.close()
        other.close()


def test_check_command_shows_the_fmu_modules():
    result = CliRunner().invoke(app, ["check", str(SCENARIOS / "fmu_moving_floor.yaml")])
    assert result.exit_code == 0, result.output
    assert "FMUModule" in result.output and "floor.force -> core.shake.force" in result.output
