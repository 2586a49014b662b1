"""``start_time:`` in a scenario (``world.start_time`` for every FMU, a module entry's own for one):
the FMU starts at that time instead of its ``DefaultExperiment startTime``, so its outputs line up with
``fmpy.simulate_fmu(start_time=...)`` row for row; bad values name file, line and field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.fmu.build import build_fmu
from dynabrain.orchestrator.kernel.errors import ScenarioError
from dynabrain.orchestrator.scenario.model import load_scenario

ROOT = Path(__file__).resolve().parents[1]
STOP = ROOT / "fmus" / "conformance" / "stop"  # declares startTime 1 s; outputs its time and its steps

pytestmark = pytest.mark.usefixtures("fmu_cache")


def write(tmp_path: Path, world: str, module: str = "", name: str = "s.yaml") -> Path:
    path = tmp_path / name
    path.write_text(f"name: st\nworld: {{step: 100ms, duration: 1s, core: null{world}}}\nmodules:\n"
                    f"  - {{name: a, fmu: '{STOP}', params: {{stop_at: 100}}{module}}}\n"
                    f"  - {{name: b, fmu: '{STOP}@fmi3', params: {{stop_at: 100}}}}\n")
    return path


def rows(path: Path, ticks: int) -> dict[str, np.ndarray]:
    with load_scenario(path).build() as w:
        out = {"a": [(w.get("a.t"), w.get("a.steps"))], "b": [(w.get("b.t"), w.get("b.steps"))]}
        for _ in range(ticks):
            w.tick()
            for m in out:
                out[m].append((w.get(f"{m}.t"), w.get(f"{m}.steps")))
    return {m: np.array(v) for m, v in out.items()}


@pytest.mark.parametrize("version", [2, 3])
def test_the_world_start_time_lines_fmus_up_with_fmpy_row_for_row(tmp_path, version):
    from fmpy import simulate_fmu

    ref = simulate_fmu(str(build_fmu(STOP, version)), start_time=2.5, stop_time=3.0, output_interval=0.1,
                       start_values={"stop_at": 100.0})
    assert ref["time"][0] == 2.5 and len(ref) == 6
    got = rows(write(tmp_path, ", start_time: 2.5s"), 5)["a" if version == 2 else "b"]
    assert np.array_equal(got[:, 1], ref["steps"])  # the same steps, row for row
    assert np.allclose(got[:, 0], ref["t"], rtol=0, atol=1e-12)  # at the same times (2.5 s, not the FMU's 1 s)


def test_a_module_start_time_overrides_the_world_and_the_fmus_own(tmp_path):
    got = rows(write(tmp_path, ", start_time: 2.5s", ", start_time: 250ms"), 2)
    assert got["a"][:, 0] == pytest.approx([0.25, 0.35, 0.45]) and got["b"][:, 0] == pytest.approx([2.5, 2.6, 2.7])
    default = rows(write(tmp_path, ""), 1)  # no start_time: each FMU's DefaultExperiment startTime (1 s)
    assert default["a"][:, 0] == pytest.approx([1.0, 1.1]) and default["b"][:, 0] == pytest.approx([1.0, 1.1])
    with load_scenario(write(tmp_path, "", ", start_time: 250ms")).build() as w:
        assert w.modules["a"].scenario_spec()["start_time"] == 0.25  # made again the same (replay, the bridge)
        assert "start_time" not in w.modules["b"].scenario_spec()


def test_a_bad_start_time_names_file_line_and_field(tmp_path):
    with pytest.raises(ScenarioError) as bad:
        load_scenario(write(tmp_path, ", start_time: -1s", ", start_time: soon")).build()
    text = str(bad.value)
    assert "s.yaml:2 [world.start_time]" in text and "zero or more" in text
    assert "s.yaml:4 [modules[0].start_time]" in text
    python = tmp_path / "p.yaml"
    python.write_text("name: p\nworld: {core: null}\nmodules:\n"
                      "  - {name: g, python: dynabrain.modules.basic:Sine, start_time: 1s}\n")
    with pytest.raises(ScenarioError, match=r"p.yaml:4 \[modules\[0\].start_time\]: start_time applies to an FMU"):
        load_scenario(python).build()
