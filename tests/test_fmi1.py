"""FMI 1.0 co-simulation FMUs (issue 28, item 1): the servo and the passthrough built here for FMI
1.0 (fmus/*/fmu.yaml list 1) run as modules and give the same bits as FMPy's own FMI 1.0 slave
stepped with the same inputs; rollback and fork are refused by name (FMI 1.0 has no FMU state);
isolated, the FMU steps alike in its own process; `check_fmu` passes; fmu.yaml refuses what an FMI
1.0 build cannot write, naming file:line [field]."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.fmu import FMUBuildError, make_fmu_module
from dynabrain.orchestrator.fmu.build import build_fmu
from dynabrain.orchestrator.fmu.check import check_fmu
from dynabrain.orchestrator.kernel.errors import ForkError, RollbackError
from dynabrain.orchestrator.kernel.world import World

FMUS = Path(__file__).resolve().parents[1] / "fmus"
pytestmark = pytest.mark.usefixtures("fmu_cache")


def fmpy_steps(name: str, params: dict[str, float], inputs: list[dict[str, float]], outputs: list[str],
               h: float, tmp: Path) -> np.ndarray:
    """Step the FMI 1.0 build of ``name`` with FMPy's FMU1Slave: each tick, set the inputs, step, read."""
    from fmpy import extract, read_model_description
    from fmpy.fmi1 import FMU1Slave

    path = build_fmu(FMUS / name, 1)
    md = read_model_description(str(path))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    folder = extract(str(path), unzipdir=str(tmp / f"{name}-fmpy"))
    slave = FMU1Slave(guid=md.guid, modelIdentifier=md.coSimulation.modelIdentifier, unzipDirectory=folder,
                      instanceName="ref")
    slave.instantiate()
    slave.setReal([vr[k] for k in params], list(params.values()))
    slave.setReal([vr[k] for k in inputs[0]], list(inputs[0].values()))
    slave.initialize(0.0)
    rows = []
    for i, values in enumerate(inputs):
        slave.setReal([vr[k] for k in values], list(values.values()))
        slave.doStep(i * h, h)
        rows.append(slave.getReal([vr[k] for k in outputs]))
    slave.terminate()
    slave.freeInstance()
    return np.array(rows)


def test_servo_steps_as_fmpys_fmi1_slave_bit_for_bit(tmp_path):
    rng = np.random.default_rng(3)
    inputs = [{"q_ref[1]": a, "q_ref[2]": b, "q[1]": c, "q[2]": d, "qd[1]": e, "qd[2]": f}
              for a, b, c, d, e, f in rng.normal(0.0, 0.5, (30, 6))]
    params = {"kp": 12.0, "kd": 1.5, "tau_max": 4.0, "lag": 0.01}
    expected = fmpy_steps("servo", params, inputs, ["tau[1]", "tau[2]"], 0.002, tmp_path)
    module = make_fmu_module("servo", f"{FMUS / 'servo'}@fmi1", base_dir=".", params=params, targets=[])
    assert module.info.version == 1 and "FMI 1.0" in module.info.label
    with World(step="2ms") as w:
        w.add_module(module)
        got = []
        for values in inputs:
            for key, value in values.items():
                w.set(f"servo.{key}", value)
            w.tick()
            got.append(w.get("servo.tau").copy())
    assert np.array_equal(np.array(got), expected)
    assert np.abs(expected).max() > 0.1  # the servo did something


def test_ports_and_fixed_parameters_and_no_rollback_or_fork():
    m = make_fmu_module("p", f"{FMUS / 'passthrough'}@fmi1", base_dir=".", params={"gain": 3.0}, targets=[])
    assert [p.name for p in m.outputs()] == ["y", "y[1]", "y[2]", "y[3]", "y[4]"]
    assert not m.param_specs()["gain"].runtime  # FMI 1.0 co-simulation sets no parameter once initialized
    assert not m.CAPABILITIES.can_rollback and not m.CAPABILITIES.can_fork and m.CAPABILITIES.feedthrough
    with World(step="1ms") as w:
        w.add_module(m)
        w.set("p.u", [1.0, -2.0, 0.5, 0.0])
        w.tick(3)
        assert np.array_equal(w.get("p.y"), [3.0, -6.0, 1.5, 0.0])
        with pytest.raises(RollbackError, match=r"module\(s\) p cannot roll back"):
            w.backtick(1)
        with pytest.raises(ForkError, match="p cannot fork"):
            w.fork()


def test_an_isolated_fmi1_fmu_steps_as_the_one_in_process():
    outs = []
    for isolate in (False, True):
        m = make_fmu_module("s", f"{FMUS / 'servo'}@fmi1", base_dir=".", params={"kp": 8.0}, targets=[],
                            isolate=isolate)
        with World(step="2ms") as w:
            w.add_module(m)
            w.set("s.q_ref", [0.3, -0.2])
            w.tick(6)
            w.set("s.q", [0.1, 0.1])
            w.tick(4)
            outs.append(w.get("s.tau").copy())
    assert np.array_equal(outs[0], outs[1]) and np.abs(outs[0]).max() > 0


def test_check_fmu_passes_an_fmi1_fmu_without_state_checks():
    report = check_fmu(f"{FMUS / 'servo'}@fmi1")
    report.assert_ok()
    assert "a run of 40 ticks with finite outputs" in report.checked and "fork" not in report.checked


def test_an_fmi1_build_refuses_types_it_cannot_write(tmp_path):
    folder = tmp_path / "enum1"
    shutil.copytree(FMUS / "passthrough", folder)
    text = (folder / "fmu.yaml").read_text()
    (folder / "fmu.yaml").write_text(text + "  - {name: mode, type: enumeration, items: [a, b], causality: input}\n")
    with pytest.raises(FMUBuildError, match=r"fmu.yaml:12 \[variables\[4\]\.type\]: an FMI 1.0 build takes real"):
        build_fmu(folder, 1)
