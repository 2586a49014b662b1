"""The paper's humanoid scenarios, run for real: each one's expectations hold, and the counterfactuals
show that the modules make the difference (without the stabilizer the slow earthquake topples the
robot; without kicks the see-saw stops; without pumping the swing does not grow)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
ROBOT_SCENARIOS = ["humanoid_stand", "earthquake", "earthquake_fast", "balance_quake", "seesaw", "swing", "breakout"]


@pytest.mark.parametrize("name", ROBOT_SCENARIOS)
def test_robot_scenario_expectations_hold(name):
    result = run_scenario(load_scenario(SCENARIOS / f"{name}.yaml"))
    failed = [f"{e.label}: {e.detail}" for e in result.expectations if not e.passed]
    assert result.error is None, result.error
    assert not failed, failed
    assert len(result.expectations) >= 3


def edited(tmp_path: Path, name: str, *edits: tuple[str, str]) -> Path:
    """A copy of a shipped scenario with text replaced (its model path made absolute)."""
    text = (SCENARIOS / f"{name}.yaml").read_text().replace("model: models/", f"model: {SCENARIOS}/models/")
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / f"{name}.yaml"
    path.write_text(text)
    return path


def final(path: Path, *signals: str) -> list:
    world = load_scenario(path).build()
    world.tick(load_scenario(path).duration_ns // world.dt_ns)
    values = [world.get(s) for s in signals]
    world.close()
    return values


def test_without_the_stabilizer_the_slow_earthquake_topples_the_robot(tmp_path):
    path = edited(tmp_path, "earthquake", ("params: {ki: 8, filter: 0.2s}", "params: {ki: 0, filter: 0.2s}"))
    (pelvis,) = final(path, "pelvis.pos")
    assert pelvis[2] < 0.15


def test_without_kicks_the_seesaw_comes_to_rest(tmp_path):
    path = edited(tmp_path, "seesaw", ("hip_offset: 45deg, knee_offset: -80deg", "hip_offset: 0, knee_offset: 0"))
    cycles, angle_rate = final(path, "swings.cycles", "core.seesaw_pivot.qd")
    assert cycles <= 1 and abs(angle_rate) < 0.01


def test_without_pumping_the_swing_does_not_grow(tmp_path):
    path = edited(tmp_path, "swing", ("hip_amplitude: -70deg, knee_amplitude: -90deg",
                                      "hip_amplitude: 0, knee_amplitude: 0"))
    amplitude, peaks = final(path, "swings.amplitude", "swings.peaks")
    assert amplitude <= peaks[0] * 1.05 or np.isnan(amplitude)


def test_dynabrain_run_prints_the_checks():
    command = [sys.executable, "-m", "dynabrain.orchestrator.cli", "run", str(SCENARIOS / "humanoid_stand.yaml"), "-q"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "the ZMP stays inside the support polygon" in done.stdout and "all checks passed" in done.stdout


def test_rolling_back_across_the_floors_arrival_and_replaying_is_exact():
    world = load_scenario(SCENARIOS / "earthquake.yaml").build()
    world.tick(700)  # 1.4 s: the stabilizer joined at 0.8 s, the floor at 1 s
    here = world.snapshot()
    world.backtick(350)  # 0.7 s: before both
    assert "quake" not in world.modules and "stabilizer" not in world.modules
    assert world.core.selection == ("pelvis",)  # the floor is frozen again
    world.tick(350)  # the scenario's events fire again on the way
    assert "quake" in world.modules and set(world.core.selection) == {"floor", "pelvis"}
    assert world.snapshot().bus.tobytes() == here.bus.tobytes()
    world.close()
