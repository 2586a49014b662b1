"""The shipped scenarios, run for real (MuJoCo), and the CLI around them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from dynabrain.orchestrator.scenario import load_world
from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"


@pytest.mark.parametrize("name", ["two_cubes", "bounce", "selection"])
def test_scenario_expectations_hold(name):
    result = run_scenario(load_scenario(SCENARIOS / f"{name}.yaml"))
    failed = [f"{e.label}: {e.detail}" for e in result.expectations if not e.passed]
    assert result.error is None
    assert not failed, failed
    assert len(result.expectations) >= 3


def test_bounce_ratios_follow_restitution_squared():
    sc = load_scenario(SCENARIOS / "bounce.yaml")
    world = sc.build()
    world.tick(round(4.5 / 0.002))
    apexes = world.get("meter.apexes")
    world.close()
    first, second = apexes[:2], apexes[2:7]
    assert abs(first[1] / first[0] / 0.09 - 1) < 0.1
    ratios = second[1:] / second[:-1] / 0.64
    assert all(abs(r - 1) < 0.1 for r in ratios), ratios


def test_selection_freezes_the_unselected_exactly():
    world = load_world(SCENARIOS / "selection.yaml")
    frozen = world.get("box_3_3.pos")
    world.tick(400)
    assert world.core.selection == ("box_0_0", "box_5_5", "box_10_2", "box_15_7", "box_19_9")
    assert (world.get("box_3_3.pos") == frozen).all()  # bit for bit where it stood
    assert world.get("box_5_5.pos")[2] < 0.06
    world.close()


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dynabrain.orchestrator.cli", *args],
                          capture_output=True, text=True, timeout=120)


def test_cli_run_and_check(tmp_path):
    done = cli("run", str(SCENARIOS / "two_cubes.yaml"), "-q")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "real-time factor" in done.stdout and "aa rests flat on the floor" in done.stdout
    checked = cli("check", str(SCENARIOS / "selection.yaml"))
    assert checked.returncode == 0 and "valid" in checked.stdout and "selected: 5" in checked.stdout


def test_cli_exit_codes(tmp_path):
    failing = tmp_path / "fail.yaml"
    failing.write_text((SCENARIOS / "two_cubes.yaml").read_text().replace("bb.z < 0.105", "bb.z > 5"))
    done = cli("run", str(failing), "-q")
    assert done.returncode == 1 and "FAIL" in done.stdout
    broken = tmp_path / "broken.yaml"
    broken.write_text("name: x\nworld: {step: 2ms, duration: 1s, core: mujoco}\nscene:\n  - box: {name: a, size: [1]}\n"
                      "  - sphere: {name: b, size: [0.1], colour: red}\n  - cone: {name: c}\n")
    done = cli("check", str(broken))
    assert done.returncode == 2
    assert "broken.yaml:4" in done.stderr and "size of length 3" in done.stderr
    assert "broken.yaml:5" in done.stderr and "did you mean 'color'" in done.stderr
    assert "broken.yaml:6" in done.stderr and "unknown shape 'cone'" in done.stderr
    missing = cli("run", str(tmp_path / "nope.yaml"))
    assert missing.returncode == 2 and "cannot read" in missing.stderr
