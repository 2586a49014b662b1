"""A property of `dynabrain check` over mutated scenarios (hypothesis): values dropped, replaced by
wrong types, huge or non-finite numbers, bad units, keys misspelt. Whatever the mutation, check
never raises: it exits 2 with every problem at a file:line, or it accepts, and then the scenario
builds and its events fire without a load-time error. Kept short (a few dozen examples); set
DYNABRAIN_HOSTILE_EXAMPLES (and DYNABRAIN_HOSTILE_SEEDS=all) to hunt longer."""

from __future__ import annotations

import contextlib
import copy
import math
import os
import re
import traceback
from pathlib import Path

import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.kernel.errors import PhysicsDivergedError
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
runner = CliRunner()

# every kind of event and expectation, early, on a small scene: cheap to build and to run to its end
SINK = """
name: sink
world: {step: 2ms, duration: 40ms, core: mujoco, seed: 3, history: 50}
core: {friction: 0.8, restitution: 0.2, gravity: [0, 0, -9.81], substeps: 2}
scene:
  - plane: {name: floor, size: [2, 2], color: grey}
  - box: {name: aa, size: [100mm, 100mm, 100mm], mass: 50g, pos: [0, 0, 0.3], color: blue, friction: 0.5}
  - sphere: {name: bb, size: [0.05], mass: 0.1, pos: [0.5, 0, 0.3], euler: [0, 0, 90]}
  - box: {name: arm, size: [0.05, 0.05, 0.3], mass: 0.2, pos: [1, 0, 1],
          joint: {hinge: {name: pivot, axis: [0, 1, 0], anchor: [0, 0, 0.15], range: [-90, 90], damping: 0.1}}}
select: [aa, bb]
modules:
  - {name: s, python: dynabrain.modules.basic:Sine, params: {amplitude: 2.0, frequency: 5Hz, phase: 10deg, unit: N*m},
     period: 4ms}
  - {name: c, python: dynabrain.modules.basic:Constant, params: {value: [1.0]}}
  - {name: g, python: dynabrain.modules.basic:Gain, params: {k: 0.5}, connect: [[c.y, g.u]]}
  - {name: h, python: dynabrain.modules.basic:Gain}
connect:
  - [s.y, core.pivot.force]
events:
  - {at: 4ms, set: {g.k: 2, core.friction: 0.9, h.u: [1.5]}}
  - {at: 6ms, add: {name: late, python: dynabrain.modules.basic:Constant, params: {value: [2.0]}}}
  - {at: 8ms, connect: [late.y, h.u, {delay: true}]}
  - {at: 10ms, make: [aa, bb, arm], place: {bb: [0.5, 0.2, 0.4], aa: {pos: [0, 0, 0.35], quat: [1, 0, 0, 0]}}}
  - {at: 12ms, no_collision: [aa, bb], make_joint: [aa, bb]}
  - {at: 14ms, disconnect: h.u}
  - {at: 16ms, remove: late}
expect:
  - {at: 10ms, that: "aa.z > 0.1 and g.k == 2 and late.y[0] == 2 and g.y[0] == 2", name: early}
  - {during: [0ms, 40ms], that: "norm(aa.pos - [0, 0, 0.3]) < 1 and t >= 0", name: stays}
  - {that: "max(abs(core.pivot.q), 0) < pi and bb.speed >= 0"}
"""
_SHIPPED = ("two_cubes", "bounce", "robot_arm", "pendulum_chain")
if os.environ.get("DYNABRAIN_HOSTILE_SEEDS") == "all":  # every shipped scenario (slower: for a long hunt)
    _SHIPPED = tuple(sorted(p.stem for p in SCENARIOS.glob("*.yaml")))
SEEDS = {"sink": SINK, **{name: (SCENARIOS / f"{name}.yaml").read_text() for name in _SHIPPED}}

NASTY = [None, True, False, 0, -1, -2.5, 1e300, -1e300, math.nan, math.inf, -math.inf, 2**64, 10**30, 1e-300,
         "", " ", "banana", "10 mss", "1e300kg", "-2ms", "1e999", "nan", "0Hz", "5 parsec", "x" * 300,
         "__class__", "aa.__init__", "[", "{", [], {}, [1, 2], [[1]], {"a": 1}, {"pos": "up"}, ["a", 1]]
"""Values put in place of any other (exponents stay small: a huge one is kernel/units.py's to bound)."""


def paths(data, here=()):
    """Every path in ``data`` (mapping keys and list indices), the root excepted."""
    out = []
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else ()
    for key, value in items:
        out.append((*here, key))
        out += paths(value, (*here, key))
    return out


def mutate(data, path, how, value):
    parent = data
    for part in path[:-1]:
        parent = parent[part]
    key = path[-1]
    if how == "drop":
        del parent[key]
    elif how == "misspell" and isinstance(parent, dict):
        parent[f"{key}x"] = parent.pop(key)
    elif how == "scale":  # a number made larger, smaller or negative; anything else left as it is
        if isinstance(parent[key], (int, float)) and not isinstance(parent[key], bool):
            parent[key] = parent[key] * value
    elif how == "twice" and isinstance(parent, list):
        parent.append(copy.deepcopy(parent[key]))
    else:
        parent[key] = copy.deepcopy(value)


@st.composite
def mutants(draw):
    name = draw(st.sampled_from(sorted(SEEDS)))
    data = yaml.safe_load(SEEDS[name])
    for _ in range(draw(st.sampled_from([1, 1, 1, 2, 3]))):
        candidates = paths(data)
        if not candidates:
            break
        path = draw(st.sampled_from(candidates))
        how = draw(st.sampled_from(["replace", "replace", "drop", "misspell", "scale", "scale", "twice"]))
        value = draw(st.sampled_from([0.5, 2.0, 10.0, -1.0, 1e6]) if how == "scale" else st.sampled_from(NASTY))
        mutate(data, path, how, value)
    return name, data


@settings(max_examples=int(os.environ.get("DYNABRAIN_HOSTILE_EXAMPLES", "25")), deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(mutant=mutants())
def test_check_of_a_mutated_scenario_refuses_with_lines_or_accepts_what_runs(tmp_path, mutant):
    name, data = mutant
    for folder in (SCENARIOS / "models", SCENARIOS.parent / "fmus"):  # what shipped scenarios name by relative path
        if not (tmp_path / folder.name).exists():
            (tmp_path / folder.name).symlink_to(folder)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False, allow_unicode=True))
    result = runner.invoke(app, ["check", str(path)])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise AssertionError(path.read_text() + "".join(traceback.format_exception(*result.exc_info)))
    assert "Traceback" not in result.output
    assert result.exit_code in (0, 2), result.output
    event(f"{name}: exit {result.exit_code}")
    if result.exit_code == 2:
        problems = [line for line in result.output.splitlines() if line.startswith("  ")]
        assert problems, result.output
        for line in problems:
            assert re.match(rf"  {re.escape(str(path))}:\d+[ :]", line), line
        return
    scenario = load_scenario(path)
    world = scenario.build()
    try:
        last_event = max(world.scheduled_ticks(), default=0)
        with contextlib.suppress(PhysicsDivergedError):  # a run-time outcome (a heavy hit, a large gravity)
            world.tick(min(last_event + 1, 100))
    finally:
        world.close()
