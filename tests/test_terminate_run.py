"""A scenario run that an FMU asks to end (fmus/conformance/stop: FMI 2.0 ``fmi2Terminated``, FMI 3.0
``terminateSimulation``) ends cleanly at that tick: `dynabrain run` says which FMU asked and where,
exits 0 when the expectations it reached hold (a terminate request is a normal end), fails one it did
not reach, and its MCAP log is complete and replays bit for bit (``replay --verify``)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.logs.read import read_index
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

ROOT = Path(__file__).resolve().parents[1]
STOP = ROOT / "fmus" / "conformance" / "stop"

pytestmark = pytest.mark.usefixtures("fmu_cache")


def scenario(tmp_path: Path, version: int, expect: str) -> Path:
    """The stop FMU (start time 1 s, asks to end at its t=2 s: world tick 9 at 100 ms) in a 5 s run."""
    path = tmp_path / f"stop{version}.yaml"
    path.write_text(f"name: stop\nworld: {{step: 100ms, duration: 5s, core: null}}\n"
                    f"modules:\n  - {{name: stopper, fmu: '{STOP}@fmi{version}'}}\nexpect:\n{expect}")
    return path


REACHED = ("  - {name: five, at: 0.5s, that: 'stopper.steps == 5'}\n"
           "  - {name: counting, during: [0.2s, 3s], that: 'stopper.steps >= 2'}\n"
           "  - {name: last, at: 0.9s, that: 'stopper.steps == 9'}\n")


@pytest.mark.parametrize("version", [2, 3])
def test_a_terminate_request_ends_the_run_cleanly_and_the_log_verifies(tmp_path, version):
    log = tmp_path / "stop.mcap"
    out = CliRunner().invoke(app, ["run", str(scenario(tmp_path, version, REACHED)), "--log", str(log), "-q"])
    text = " ".join(out.output.split())
    end_tick, end_t = (9, "0.9") if version == 2 else (10, "1")  # FMI 3.0 asks on an OK step: it stands
    assert out.exit_code == 0, text  # a normal end: every expectation it reached holds
    assert f"run ended: module 'stopper' asked to end the simulation at tick {end_tick} (t={end_t} s)" in text
    assert f"FMI {version}.0) asked to end the simulation in its step from t=1.9 s" in text
    assert "run stopped" not in text and "all checks passed" in text
    index = read_index(log)
    assert index.report.complete and not index.report.damaged
    [end] = [e["detail"] for e in index.events if e["kind"] == "run_end"]
    assert (end["ticks"], end["error"], end["ok"]) == (end_tick, None, True)
    assert end["ended"].startswith(f"module 'stopper' asked to end the simulation at tick {end_tick}")
    result = verify(log)
    assert result.ok and result.last_tick == end_tick, result.divergence


def test_an_expectation_after_the_end_is_not_reached_and_fails(tmp_path):
    path = scenario(tmp_path, 2, REACHED + "  - {name: late, at: 3s, that: 'stopper.steps == 30'}\n")
    result = run_scenario(load_scenario(path))
    assert result.error is None and result.ticks == 9 and result.ended_by == "stopper"
    assert "at tick 9 (t=0.9 s)" in result.ended and not result.ok
    late = result.expectations[-1]
    assert late.passed is False and late.detail.startswith("not reached: the run ended at tick 9 (t=0.9 s): module "
                                                           "'stopper' asked to end the simulation")
    assert all(e.passed for e in result.expectations[:-1])
    assert result.expectations[1].detail.startswith("held up to tick 9, where module 'stopper' asked")  # cut short
    out = CliRunner().invoke(app, ["run", str(path), "-q"])
    assert out.exit_code == 1 and "not reached" in out.output


def test_an_expectation_at_the_last_tick_is_checked_there(tmp_path):
    """The tick the run ends at is checked (the world stands at its start: 9 steps done)."""
    result = run_scenario(load_scenario(scenario(tmp_path, 2, "  - {at: 0.9s, that: 'stopper.steps == 8'}\n")))
    assert result.ended is not None and result.expectations[0].passed is False
    assert "false at t=0.9s" in result.expectations[0].detail
