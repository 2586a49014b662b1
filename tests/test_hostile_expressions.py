"""Expectation expressions are parsed and checked against a whitelist, never handed to eval: the attack
of issue 17 and other escapes are refused before anything runs, naming the piece; what the shipped
scenarios write is accepted and means what Python would make of it."""

from __future__ import annotations

import glob
import math
import textwrap
import types
from pathlib import Path

import numpy as np
import pytest
import yaml

from dynabrain.orchestrator.kernel.errors import ScenarioError
from dynabrain.orchestrator.scenario.expect import FUNCTIONS, Expectation, Expression, ExpressionError, Reader
from dynabrain.orchestrator.scenario.model import load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
ATTACK = "[aa][0].__init__.__globals__['__builtins__']['__import__']('os').system('id > x') == 0"

ESCAPES = [
    (ATTACK, "__init__"),
    ("getattr(aa, 'x') > 0", "getattr"),
    ("aa.__class__ == 1", "__class__"),
    ("().__class__.__bases__[0].__subclasses__()", "__subclasses__"),
    ("(lambda: 1)() == 1", "lambda"),
    ("__import__('os').system('id')", "__import__"),
    ("(1).real == 1", "(1).real"),
    ("'abc'.upper() == 'ABC'", "upper"),
    ("[1, 2].copy() == 1", "copy"),
    ("aa._core.model", "_core"),
    ("[x for x in aa.pos] == 1", "comprehension"),
    ("f'{aa}' == ''", "f-string"),
    ("(x := 1) == 1", "assignment"),
    ("10**10**10 > 0", "10**10**10"),
    ("2**100000 * 2**100000 > 0", "bits"),
    ("'a' * 1000000000 == ''", "arithmetic takes numbers"),
    ("1 << 100000", "LShift"),
    ("aa.pos[None] == 1", "None"),
    ("norm(aa.pos, ord=2) > 0", "keyword"),
    ("max(*aa.pos) > 0", "starred"),
    ("{'a': 1} == 1", "mapping"),
    ("abs == abs", "function"),
    ("aa is aa", "Is"),
    ("aa.z in [1]", "In"),
    ("~1", "~"),
    ("t.real > 0", "t has no attributes"),
    ("max.__self__", "__self__"),
    ("-" * 60 + "1", "deeper"),
    ("1" * 1001, "longer"),
    ("aa.z >", "not valid"),
]


@pytest.mark.parametrize(("text", "piece"), ESCAPES, ids=[e[1] for e in ESCAPES])
def test_an_escape_is_refused_naming_the_piece(text, piece):
    with pytest.raises(ExpressionError) as err:
        Expression(text)
    assert piece in str(err.value)


def test_the_attack_is_refused_by_check_with_file_and_line_and_never_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "attack.yaml"
    path.write_text(textwrap.dedent(f"""\
        name: attack
        world: {{step: 2ms, duration: 10ms, core: mujoco}}
        scene:
          - box: {{name: aa, size: [0.1, 0.1, 0.1], mass: 1, pos: [0, 0, 0.5]}}
        expect:
          - {{at: 10ms, that: "{ATTACK}"}}
        """))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path).build()
    (problem,) = err.value.problems
    assert (problem.line, problem.field) == (6, "expect[0].that") and "__init__" in problem.message
    assert not (tmp_path / "x").exists()


def test_values_are_numbers_whatever_a_parameter_holds(tmp_path):
    """A string parameter is readable and comparable, but no arithmetic repeats it."""
    path = tmp_path / "s.yaml"
    path.write_text(textwrap.dedent("""\
        name: s
        world: {step: 1ms, duration: 2ms, core: null}
        modules:
          - {name: s, python: dynabrain.modules.basic:Sine, params: {unit: N}}
        expect:
          - {at: 1ms, that: "s.unit == 'N' and len(s.unit) == 1", name: compared}
          - {at: 1ms, that: "len(s.unit * 1000000000) > 0", name: repeated}
          - {at: 1ms, that: "round(s.y, -1000000000) == 0", name: rounded}
        """))
    compared, repeated, rounded = run_scenario(load_scenario(path)).expectations
    assert compared.passed
    assert not repeated.passed and "arithmetic takes numbers" in repeated.detail
    assert not rounded.passed and "digits" in rounded.detail


def test_bare_names_and_unknown_fields_are_named(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(textwrap.dedent("""\
        name: s
        world: {step: 1ms, duration: 2ms, core: mujoco}
        scene:
          - box: {name: aa, size: [0.1, 0.1, 0.1], mass: 1, pos: [0, 0, 0.5]}
        modules:
          - {name: s, python: dynabrain.modules.basic:Sine}
        expect:
          - {that: "aa > 0"}
          - {that: "s == 1"}
          - {that: "aa.pos.T[0] > 0"}
          - {that: "s.y.real > 0"}
          - {that: "bb.z > 0"}
        """))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path).build()
    text = "\n".join(map(str, err.value.problems))
    assert "s.yaml:8 [expect[0].that]: in 'aa > 0': 'aa' is a body; read one of its fields" in text
    assert "s.yaml:9 [expect[1].that]: in 's == 1': 's' is a module" in text
    assert "s.yaml:10" in text and "body 'aa' has no field 'pos.T'" in text
    assert "s.yaml:11" in text and "s.y.real" in text
    assert "s.yaml:12" in text and "unknown name 'bb'" in text


def _shipped_expressions() -> list[str]:
    out = []
    for file in sorted(glob.glob(str(SCENARIOS / "*.yaml"))):
        out += [e["that"] for e in (yaml.safe_load(Path(file).read_text()) or {}).get("expect", [])]
    return out


class _FakeReader(Reader):
    """Reads the same made-up values an eval namespace holds (see the test below)."""

    def __init__(self, values: dict[str, types.SimpleNamespace], time: float):
        self.values, self._time = values, time

    @property
    def time(self) -> float:
        return self._time

    def read(self, base: str, chain: tuple[str, ...]):
        value = self.values[base]
        for part in chain:
            value = getattr(value, part)
        return value


def _fake(rng: np.random.Generator) -> types.SimpleNamespace:
    """Any name's fields: floats for x y z speed, arrays elsewhere (long enough for every index used)."""
    class Fake(types.SimpleNamespace):
        def __getattr__(self, key):  # a module's port or a dotted port's next part
            value = Fake() if key in ("floor_tilt", "pivot") else rng.normal(size=20)
            setattr(self, key, value)
            return value

    fake = Fake(x=rng.normal(), y=rng.normal(), z=rng.normal(), speed=abs(rng.normal()),
                pos=rng.normal(size=3), vel=rng.normal(size=3), angvel=rng.normal(size=3), quat=rng.normal(size=4))
    return fake


def test_every_shipped_expression_is_accepted_and_agrees_with_python():
    expressions = _shipped_expressions()
    assert len(expressions) > 50
    for seed in range(3):
        rng = np.random.default_rng(seed)
        for text in expressions:
            expression = Expression(text)
            names = {r.base for r in expression.reads} | set(expression.names)
            values = {name: _fake(rng) for name in names}
            namespace = {**FUNCTIONS, "pi": math.pi, "t": 1.5, **values}
            expected = _outcome(lambda: eval(text, {"__builtins__": {}}, namespace))  # noqa: B023 (the reference)
            assert _outcome(lambda: expression.evaluate(_FakeReader(values, 1.5))) == expected, text  # noqa: B023


def _outcome(evaluate) -> tuple:
    """What an evaluation gives: its truth (as `Expectation.check` takes it) or the kind of error it raises."""
    try:
        return "value", bool(np.all(evaluate()))
    except Exception as exc:
        return "error", type(exc).__name__


def test_constants_fold_once_and_a_list_is_an_array():
    expression = Expression("abs(aa.z - (2.70711 - 0.5 * 9.81 * 0.3**2)) < [1, 2][0] and t >= 0 and pi > 3")
    reader = _FakeReader({"aa": types.SimpleNamespace(z=2.26)}, 0.0)
    assert expression.evaluate(reader) is True
    exp = Expectation("aa.z > 100", 0, 0, "high")
    assert exp.check(types.SimpleNamespace(time=0.0, tick_count=0), reader) is False
    assert "aa.z = 2.26" in exp.detail
