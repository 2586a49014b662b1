"""Python modules and their FMU twins are interchangeable in a scenario and give the same motion.

Servo: `dynabrain.modules.servo:Servo` against `fmus/servo` (FMI 2.0) on two hanging arms; the same
law computed in C and in numpy, so the joint trajectories agree to rounding (stated: 1e-9 rad).
Floor: `dynabrain.modules.floor:MovingFloor` against `fmus/moving_floor` driving a table on a slide;
the same law, so the table's trajectory agrees to 1e-9 m.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
FMU_SERVO = "{name: servo, fmu: fmus/servo, params: {kp: 20, kd: 1, tau_max: 5, lag: 10ms}}"
PY_SERVO = ("{name: servo, python: 'dynabrain.modules.servo:Servo', targets: [j1, j2], "
            "params: {kp: 20, kd: 1, tau_max: 5, lag: 10ms}}")
FMU_FLOOR = "{name: floor, fmu: fmus/moving_floor, params: {amplitude: 40mm, frequency: 2Hz, mass: 5kg}}"
PY_FLOOR = ("{name: floor, python: 'dynabrain.modules.floor:MovingFloor', "
            "params: {amplitude: 40mm, frequency: 2Hz, mass: 5kg, kp: 4000, kd: 200, ramp: 0.25s}}")


def trajectory(tmp_path: Path, scenario: str, old: str, new: str | None, signals: list[str],
               ticks: int) -> np.ndarray:
    text = (SCENARIOS / f"{scenario}.yaml").read_text()
    assert old in text
    path = tmp_path / f"{scenario}-{'py' if new else 'fmu'}.yaml"
    text = text if new is None else text.replace(old, new)
    path.write_text(text.replace("fmu: fmus/", f"fmu: {SCENARIOS.parent / 'fmus'}/"))  # the copy lives elsewhere
    world = load_scenario(path).build()
    rows = []
    for _ in range(ticks):
        world.tick()
        rows.append(np.concatenate([np.atleast_1d(world.get(s)) for s in signals]))
    world.close()
    return np.array(rows)


def test_servo_and_its_fmu_twin_move_the_arms_alike(tmp_path):
    signals = ["core.j1.q", "core.j2.q", "core.j1.qd"]
    fmu = trajectory(tmp_path, "fmu_servo", FMU_SERVO, None, signals, 1000)
    py = trajectory(tmp_path, "fmu_servo", FMU_SERVO, PY_SERVO, signals, 1000)
    assert np.abs(fmu[:, :2]).max() > 0.3  # the arms really move
    assert np.abs(fmu - py).max() < 1e-9


def test_moving_floor_and_its_fmu_twin_shake_the_table_alike(tmp_path):
    signals = ["core.shake.q", "floor.position", "floor.force"]
    fmu = trajectory(tmp_path, "fmu_moving_floor", FMU_FLOOR, None, signals, 750)
    py = trajectory(tmp_path, "fmu_moving_floor", FMU_FLOOR, PY_FLOOR, signals, 750)
    assert np.abs(fmu[:, 0]).max() > 0.035  # the table really shakes, 40 mm
    assert np.abs(fmu[:, :2] - py[:, :2]).max() < 1e-9
    assert np.abs(fmu[:, 2] - py[:, 2]).max() < 1e-6  # N, from differences of nearly equal terms
