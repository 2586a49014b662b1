"""Swing learning (examples/swing_learning.py, scenarios/swing_learning.yaml): a few generations of
CMA-ES on a short horizon learn a policy that beats random ones, SwingPolicy with the hand rule's
weights is the hand rule, and the shipped learned policy beats the hand rule as its scenario says."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from dynabrain.modules.policies import SwingPolicy
from dynabrain.orchestrator import Batch, check_module, load_world
from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("swing_learning_example", ROOT / "examples" / "swing_learning.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # (dataclasses look their module up)
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]


def test_a_few_generations_beat_random_policies(example):
    """4 generations of 8 on 6 s episodes (fixed seed) beat each of 8 random policies drawn as CMA-ES
    draws its first generation; the learned weights give the same amplitude when run again."""
    ticks = 3000
    with load_world(example.LEARNING) as world:
        found = example.train(world, generations=4, ticks=ticks, popsize=8, seed=1, log=lambda line: None)
        with Batch(world, backend="serial") as batch:
            random = example.amplitudes(batch, ticks, np.random.default_rng(7).normal(size=(8, 3)) * example.SCALE)
            again = example.amplitudes(batch, ticks, np.array([list(found.weights.values())]))
    assert found.episodes == 32 and len(found.generations) == 4
    assert found.amplitude > random.max() and found.amplitude > 2 * np.median(random), (found, random)
    assert again[0] == found.amplitude


def test_swing_policy_with_the_hand_rules_weights_is_the_hand_rule():
    """w_angle 0, w_rate 1/rate_scale, bias 0 is PhasePump: the same leg offsets tick for tick."""
    hand = load_world(ROOT / "scenarios" / "swing.yaml")
    mine = load_world(ROOT / "scenarios" / "swing_learning.yaml")
    for name, value in {"w_angle": 0.0, "w_rate": 1 / 0.02, "bias": 0.0}.items():
        mine.set(f"policy.{name}", value)
    a = hand.run(500, record=["pump.hip", "pump.knee", "core.swing_pivot.q"])
    b = mine.run(500, record=["policy.hip", "policy.knee", "core.swing_pivot.q"])
    assert np.array_equal(a["pump.hip"], b["policy.hip"]) and np.array_equal(a["pump.knee"], b["policy.knee"])
    assert np.array_equal(a["core.swing_pivot.q"], b["core.swing_pivot.q"])
    hand.close()
    mine.close()
    check_module(SwingPolicy("policy", w_angle=20.0, w_rate=-1.0, bias=0.3)).assert_ok()


def test_the_shipped_learned_policy_beats_the_hand_rule():
    result = run_scenario(load_scenario(ROOT / "scenarios" / "swing_learning.yaml"))
    failed = [f"{e.label}: {e.detail}" for e in result.expectations if not e.passed]
    assert result.error is None and not failed, (result.error, failed)
    assert any("0.1071" in e.label for e in result.expectations)
