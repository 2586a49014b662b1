"""Issue 24, item 4: what a run would refuse, `check` refuses, with file:line [field]: durations inside a
module's own parameters (a servo's ``sequence``, written as text or numbers), counts that would lay
out an enormous bus, lists beyond `MAX_PARAM_ITEMS`, and constant parts of an expression, calls included.
"""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.kernel.errors import ScenarioError, UnitError
from dynabrain.orchestrator.scenario import limits
from dynabrain.orchestrator.scenario.model import load_world

runner = CliRunner()
ARM = """\
name: arm
world: {{step: 2ms, duration: 20ms, core: mujoco}}
scene:
  - plane: {{name: floor}}
  - box: {{name: base, size: [0.2, 0.2, 0.1], pos: [0, 0, 0.05], mass: 5, joint: fixed}}
  - box: {{name: arm, size: [0.05, 0.05, 0.3], pos: [0, 0, 0.3], mass: 1, parent: base,
          joint: {{hinge: {{name: j1, axis: [0, 1, 0], anchor: [0, 0, -0.15]}}}}}}
modules:
  - name: servo
    python: dynabrain.modules.servo:Servo
    targets: [j1]
    params: {{sequence: [{{pose: [0.5], duration: {duration}}}]}}
{more}"""


def problems(tmp_path, duration="0.5s", more="") -> list:
    path = tmp_path / "s.yaml"
    path.write_text(ARM.format(duration=duration, more=more))
    try:
        load_world(path).close()
    except ScenarioError as exc:
        return exc.problems
    return []


@pytest.mark.parametrize("duration", ["1e300", "1e300s", "2e6s", "3e9ms", "1e7"])
def test_a_servo_step_longer_than_max_duration_is_refused_at_check(tmp_path, duration):
    (problem,) = problems(tmp_path, duration)
    assert problem.line == 12 and problem.field == "modules[0].params.sequence", problem
    assert "MAX_DURATION_S" in problem.message or "at most 1e+06" in problem.message
    done = runner.invoke(app, ["check", str(tmp_path / "s.yaml")])
    assert done.exit_code == 2 and "s.yaml:12" in done.output
    ran = runner.invoke(app, ["run", str(tmp_path / "s.yaml")])
    assert ran.exit_code == 2 and "Traceback" not in ran.output  # refused before the run, not an OverflowError in it


def test_a_servo_sequence_within_the_limits_still_runs(tmp_path):
    assert problems(tmp_path, "500ms") == []
    assert problems(tmp_path, "1e5s") == []


def test_a_count_that_would_lay_out_a_huge_bus_is_refused_at_check(tmp_path):
    noise = "  - {name: noise, python: dynabrain.modules.basic:Noise, params: {n: 1000000000000}}\n"
    (problem,) = problems(tmp_path, more=noise)
    assert problem.line == 13 and "MAX_PORT_VALUES" in problem.message


def test_lists_and_quantities_in_parameters_are_bounded():
    with pytest.raises(UnitError, match="MAX_PARAM_ITEMS"):
        limits.check_magnitudes([0.0] * (limits.MAX_PARAM_ITEMS + 1), "p")
    with pytest.raises(UnitError, match=r"within ±1e\+15"):
        limits.check_magnitudes({"gain": "5e20"}, "p")
    with pytest.raises(UnitError, match="MAX_DURATION_S"):
        limits.check_magnitudes([{"period": "2e6s"}], "p")
    limits.check_magnitudes({"label": "a name", "delay": "20ms", "x": "1e14"}, "p")  # text and small values pass


@pytest.mark.parametrize("that, why", [("sqrt(-1) < t", "math domain error"),
                                       ("round(1e308 * 10) > t", "OverflowError"),
                                       ("t > max(1, sqrt(-4))", "math domain error")])
def test_constant_calls_in_an_expression_are_evaluated_at_check(tmp_path, that, why):
    path = tmp_path / "e.yaml"
    path.write_text(f'name: e\nworld: {{step: 2ms, duration: 10ms, core: null}}\nexpect:\n  - {{that: "{that}"}}\n')
    with pytest.raises(ScenarioError) as caught:
        load_world(path)
    (problem,) = caught.value.problems
    assert problem.line == 4 and problem.field == "expect[0].that" and why in problem.message
