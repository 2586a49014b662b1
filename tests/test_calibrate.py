"""Calibration (orchestrator/brain/calibrate.py): the brain's world is fitted to what a "real" world (the
same scene with other coefficients) recorded, with batches of real MuJoCo futures: a box's friction from
how far a push slid it, a ball's restitution from its bounce; a parameter the motion never exercised is
reported as not identifiable, with no estimate; bad input is refused before anything runs."""

from __future__ import annotations

import numpy as np
import pytest

from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator import BodySpec, SceneSpec, World
from dynabrain.orchestrator.brain.calibrate import CalibrationError, calibrate

TICKS = 400


def _scene(friction: float | None = None, restitution: float | None = None) -> World:
    floor = BodySpec(name="floor", shape="plane", size=(), color="grey")
    box = BodySpec(name="box", shape="box", size=(0.1, 0.1, 0.1), pos=(0, 0, 0.0505), mass=0.5, color="red")
    ball = BodySpec(name="ball", shape="sphere", size=(0.05,), pos=(1.0, 0, 0.4), mass=0.2, color="blue")
    core = MujocoCore("core", SceneSpec(bodies=(floor, box, ball)), friction=0.6, restitution=0.3)
    world = World("w", step="2ms", history=20, core=core)
    if friction is not None:
        world.set_material("box", friction=friction)
    if restitution is not None:
        world.set_material("ball", restitution=restitution)
    return world


@pytest.fixture(scope="module")
def observed():
    push = np.full((TICKS, 6), np.nan)
    push[:60, 0], push[:60, 1:] = 1.5, 0.0  # a hand pushes the box for 0.12 s, then lets it slide
    real = _scene(friction=0.35, restitution=0.7)
    try:
        seen = real.run(TICKS, inputs={"core.box.velocity": push}, record=["core.box.pos", "core.ball.pos"])
    finally:
        real.close()
    return push, seen


@pytest.fixture()
def brain():
    world = _scene()
    yield world
    world.close()


def test_friction_is_recovered_and_an_unexercised_parameter_is_said_flat(brain, observed):
    push, seen = observed
    before = brain.export_state()
    fit = calibrate(brain, {"core.box.pos": seen["core.box.pos"]},
                    {"core.box.friction": (0.1, 1.5), "core.box.restitution": (0.0, 0.9)},
                    inputs={"core.box.velocity": push}, backend="serial", budget=120)
    assert abs(fit.estimates["core.box.friction"] - 0.35) < 0.035  # within 10%
    assert fit.identifiable == {"core.box.friction": True, "core.box.restitution": False}
    assert fit.estimates["core.box.restitution"] is None
    assert fit.residual_after < 0.1 * fit.residual_before
    assert "not identifiable" in fit.describe()
    assert brain.export_state() == before  # the world itself does not change
    assert fit.apply(brain) == {"core.box.friction": fit.estimates["core.box.friction"]}
    assert brain.core.material("box").friction == pytest.approx(fit.estimates["core.box.friction"])
    assert brain.core.material("box").restitution is None
    again = brain.run(TICKS, inputs={"core.box.velocity": push}, record=["core.box.pos"])["core.box.pos"]
    assert np.max(np.abs(again - seen["core.box.pos"])) < 0.005  # the brain now predicts what happened


def test_restitution_from_an_observed_bounce(brain, observed):
    _, seen = observed
    fit = calibrate(brain, {"core.ball.pos": seen["core.ball.pos"]}, {"core.ball.restitution": (0.0, 0.95)},
                    backend="serial", budget=80)
    assert abs(fit.estimates["core.ball.restitution"] - 0.7) < 0.05
    assert fit.identifiable["core.ball.restitution"]


def test_bad_input_is_refused_before_anything_runs(brain, observed):
    _, seen = observed
    box = seen["core.box.pos"]
    with pytest.raises(CalibrationError, match=r"observed\['core.box.pos'\] has shape \(400,\)"):
        calibrate(brain, {"core.box.pos": box[:, 0]}, {"core.box.friction": (0.1, 1.5)})
    with pytest.raises(CalibrationError, match=r"covers 10 ticks where the others cover 400"):
        calibrate(brain, {"core.box.pos": box, "core.ball.pos": seen["core.ball.pos"][:10]},
                  {"core.box.friction": (0.1, 1.5)})
    with pytest.raises(CalibrationError, match=r"observed\['core.bx.pos'\]"):
        calibrate(brain, {"core.bx.pos": box}, {"core.box.friction": (0.1, 1.5)})
    with pytest.raises(CalibrationError, match=r"params\['core.box.friction'\] is \(1.5, 0.1\)"):
        calibrate(brain, {"core.box.pos": box}, {"core.box.friction": (1.5, 0.1)})
    with pytest.raises(CalibrationError, match=r"params\['core.nothing'\]"):
        calibrate(brain, {"core.box.pos": box}, {"core.nothing": (0.0, 1.0)})
    with pytest.raises(CalibrationError, match=r"inputs\['core.box.velocity'\] has shape \(5, 6\)"):
        calibrate(brain, {"core.box.pos": box}, {"core.box.friction": (0.1, 1.5)},
                  inputs={"core.box.velocity": np.zeros((5, 6))})
