"""The Exudyn scenarios, run for real: every expectation holds, on Exudyn and, for the scenarios made
of primitives, on MuJoCo too (one word: `Scenario.build(core=...)`); the flexible one is refused by
MuJoCo, naming the feature and the core."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from dynabrain.orchestrator.kernel.errors import ScenarioError
from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
BOTH = ["two_cubes_exudyn", "pendulum_chain", "robot_arm"]


def run(name: str, core: str):
    scenario = load_scenario(SCENARIOS / f"{name}.yaml")
    result = run_scenario(scenario, scenario.build(core=core))
    failed = [f"{e.label}: {e.detail}" for e in result.expectations if not e.passed]
    return result, failed


@pytest.mark.parametrize("core", ["exudyn", "mujoco"])
@pytest.mark.parametrize("name", BOTH)
def test_scenario_holds_on_both_cores(name, core):
    result, failed = run(name, core)
    assert result.error is None
    assert not failed, failed
    assert len(result.expectations) >= 4


def test_rope_swing_expectations_hold(tmp_path):
    os.chdir(tmp_path)
    result, failed = run("rope_swing_exudyn", "exudyn")
    assert result.error is None
    assert not failed, failed
    assert len(result.expectations) >= 8
    assert not list(tmp_path.iterdir())  # Exudyn wrote no solution, sensor or restart files


def test_mujoco_refuses_the_flexible_scenario_naming_feature_and_core():
    with pytest.raises(ScenarioError) as info:
        load_scenario(SCENARIOS / "rope_swing_exudyn.yaml").build(core="mujoco")
    first = str(info.value.problems[0])
    assert "rope_swing_exudyn.yaml" in first and "flexible body" in first and "mujoco" in first
    assert "cable" in first and "line 17" in first


def test_bounce_follows_restitution_on_exudyn():
    result, failed = run("bounce", "exudyn")  # MuJoCo's scenario, by one word: restitution is calibrated
    assert result.error is None and not failed, failed


def test_exudyn_refuses_a_model_file_naming_feature_and_core(tmp_path):
    (tmp_path / "arm.xml").write_text("<mujoco><worldbody/></mujoco>")
    (tmp_path / "s.yaml").write_text("name: s\nworld: {step: 2ms, duration: 1s, core: exudyn}\n"
                                     "scene: {model: arm.xml}\n")
    with pytest.raises(ScenarioError, match=r"model file .* not supported by the exudyn core"):
        load_scenario(tmp_path / "s.yaml").build()


def test_cable_fields_are_checked_with_file_and_line(tmp_path):
    (tmp_path / "c.yaml").write_text(
        "name: c\nworld: {step: 2ms, duration: 1s, core: exudyn}\nscene:\n"
        "  - box: {name: seat, size: [0.2, 0.2, 0.02], pos: [0, 0, 0.5]}\n"
        "  - cable: {name: a, from: [0, 0, 1], to: [0, 0, 0.5], radiuss: 5mm}\n"
        "  - cable: {name: b, from: [0, 0, 1], to: [0, 0, 1], segments: 0}\n"
        "  - cable: {name: d, from: [0, 0, 1], to: [0, 0, 0.5], attach: [world, seet]}\n")
    with pytest.raises(ScenarioError) as info:
        load_scenario(tmp_path / "c.yaml").build()
    text = str(info.value)
    assert "c.yaml:5" in text and "did you mean 'radius'" in text
    assert "c.yaml:6" in text and "ends must differ" in text and "segments is a whole number" in text
    assert "c.yaml:7" in text and "'seet'" in text and "did you mean 'seat'" in text
