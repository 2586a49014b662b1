"""Scenario validation: every problem reported at once, each with file, line and field."""

from __future__ import annotations

import textwrap

import pytest

from dynabrain.orchestrator.kernel.errors import ScenarioError
from dynabrain.orchestrator.kernel.units import parse_duration_ns
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario.model import load_scenario


def problems_of(tmp_path, text: str) -> list[str]:
    path = tmp_path / "s.yaml"
    path.write_text(textwrap.dedent(text))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path).build()
    return [str(p) for p in err.value.problems]


SIGNALS = """
name: t
world: {step: 1ms, duration: 10ms, core: null}
modules:
  - {name: s, python: dynabrain.modules.basic:Sine, params: {frequency: 2Hz}}
  - {name: g, python: dynabrain.modules.basic:Gain}
"""


def test_malformed_yaml_has_a_line(tmp_path):
    (msg,) = problems_of(tmp_path, "name: t\nworld: {step: 1ms\nmodules: []\n")
    assert "malformed YAML" in msg and "s.yaml:3" in msg


def test_unknown_keys_suggest_the_closest(tmp_path):
    found = problems_of(tmp_path, """
        name: t
        wrld: {step: 1ms}
        modules:
          - {name: g, pyton: dynabrain.modules.basic:Gain}
        """)
    assert any("s.yaml:3" in p and "'wrld'" in p and "did you mean 'world'" in p for p in found)
    assert any("s.yaml:5" in p and "modules[0].pyton" in p and "did you mean 'python'" in p for p in found)


def test_every_problem_is_reported_together(tmp_path):
    found = problems_of(tmp_path, SIGNALS + """
  - {name: x, python: dynabrain.modules.basic:Nope}
  - {name: y, python: no_such_package.mod:Cls}
  - {name: z, python: dynabrain.modules.basic:Gain, params: {kk: 2}}
  - {name: w, python: dynabrain.modules.basic:Counter, period: 1.5ms}
  - {name: s, python: dynabrain.modules.basic:Counter}
connect:
  - [s.yy, g.u]
expect:
  - {at: 5ms, that: "gg.y > 0"}
events:
  - {at: 2ms, set: {g.kay: 3}}
""")
    text = "\n".join(found)
    assert len(found) == 8, text
    assert "has no class 'Nope'" in text
    assert "'no_such_package.mod:Cls' is not allowed" in text and "--allow-python no_such_package" in text
    assert "no parameter 'kk' (did you mean 'k'?)" in text
    assert "not a whole multiple" in text
    assert "'s' is used twice" in text
    assert "no output port 'yy' (did you mean 'y'?)" in text
    assert "unknown name 'gg'" in text and "did you mean 'g'" in text
    assert "g.kay" in text and "did you mean 'g.k'" in text
    assert all("s.yaml:" in p for p in found)


def test_bad_units(tmp_path):
    found = problems_of(tmp_path, """
        name: t
        world: {step: 1 parsec, duration: 2kg, core: null}
        """)
    text = "\n".join(found)
    assert "duration" in text and "is a mass, expected a time" in text


def test_bad_step_unit_is_named(tmp_path):
    found = problems_of(tmp_path, """
        name: t
        world: {step: 3xs, duration: 1s, core: null}
        """)
    assert any("s.yaml:3 [world.step]" in p and "unknown unit 'xs'" in p and "did you mean" in p for p in found)


def test_algebraic_loop_in_a_scenario(tmp_path):
    found = problems_of(tmp_path, SIGNALS + """
  - {name: h, python: dynabrain.modules.basic:Gain}
connect:
  - [g.y, h.u]
  - [h.y, g.u]
""")
    assert any("algebraic loop" in p and "g.y -> h.u" in p and "s.yaml:11 [connect[1]]" in p for p in found)


def test_expectation_outside_the_run_and_bad_syntax(tmp_path):
    found = problems_of(tmp_path, SIGNALS + """
expect:
  - {at: 1s, that: "s.y > 0"}
  - {that: "s.y >"}
""")
    assert any("outside the run" in p for p in found) and any("not valid" in p for p in found)


def test_shape_mismatch_names_the_line(tmp_path):
    found = problems_of(tmp_path, SIGNALS + """
connect:
  - [s.y, g.u]
""")
    assert any("shape mismatch" in p and "s.yaml:9 [connect[0]]" in p for p in found), found


def test_a_valid_signal_scenario_runs(tmp_path):
    from dynabrain.orchestrator.scenario.runner import run_scenario

    path = tmp_path / "ok.yaml"
    path.write_text(SIGNALS.replace("10ms", "300ms") + """
expect:
  - {at: 125ms, that: "abs(s.y - 1) < 1e-9", name: sine peak at a quarter period}
  - {at: 250ms, that: "abs(s.y) < 1e-9", name: zero at half a period}
  - {at: 300ms, that: "s.y > 0", name: deliberately false}
""")
    result = run_scenario(load_scenario(path))
    assert [e.passed for e in result.expectations] == [True, True, False]
    assert "s.y = " in result.expectations[2].detail


def test_durations_are_exact_integers():
    assert parse_duration_ns("2ms") == 2_000_000
    assert parse_duration_ns("0.1ms") == 100_000
    assert parse_duration_ns("500Hz") == 2_000_000
    assert parse_duration_ns(0.003) == 3_000_000
    assert World(step="0.5ms").dt_ns == 500_000


def test_expectations_may_name_modules_events_add_and_dotted_ports(tmp_path):
    from dynabrain.orchestrator.scenario.runner import run_scenario

    path = tmp_path / "late.yaml"
    path.write_text("""
name: late
world: {step: 1ms, duration: 50ms, core: mujoco}
scene:
  - box: {name: arm, size: [0.05, 0.05, 0.3], mass: 0.2, pos: [0, 0, 1],
          joint: {hinge: {name: pivot, axis: [0, 1, 0], anchor: [0, 0, 0.15]}}}
events:
  - {at: 10ms, add: {name: late, python: "dynabrain.modules.basic:Sine", params: {frequency: 5Hz}}}
  - {at: 20ms, set: {late.amplitude: 2.0}}
expect:
  - {at: 50ms, that: "late.amplitude == 2.0 and abs(late.y - 2.0) < 1e-9", name: added module read}
  - {at: 50ms, that: "core.pivot.q == 0 and core.pivot.qd == 0", name: dotted port read}
""")
    result = run_scenario(load_scenario(path))
    assert [e.passed for e in result.expectations] == [True, True], [e.detail for e in result.expectations]
    bad = tmp_path / "bad.yaml"
    bad.write_text(path.read_text().replace("core.pivot.qd", "core.pivot.qq").replace("20ms, set", "5ms, set"))
    found = problems_of(tmp_path, bad.read_text())
    text = "\n".join(found)
    assert "core.pivot.qq" in text and "late.amplitude" in text, text


def test_events_are_checked_against_the_structure_earlier_events_leave(tmp_path):
    found = problems_of(tmp_path, """
        name: t
        world: {step: 1ms, duration: 50ms, core: mujoco}
        scene:
          - box: {name: aa, size: [0.1, 0.1, 0.1], mass: 1, pos: [0, 0, 0.5]}
          - box: {name: bb, size: [0.1, 0.1, 0.1], mass: 1, pos: [1, 0, 0.5]}
          - box: {name: cc, size: [0.1, 0.1, 0.1], mass: 1, pos: [2, 0, 0.5], joint: fixed}
        select: [aa]
        modules:
          - {name: c, python: dynabrain.modules.basic:Constant, params: {value: [1.0]}}
          - {name: g, python: dynabrain.modules.basic:Gain}
        connect:
          - [c.y, g.u]
        events:
          - {at: 1ms, remove: c}
          - {at: 2ms, remove: c}
          - {at: 3ms, disconnect: g.u}
          - {at: 4ms, set: {c.value: [2.0]}}
          - {at: 5ms, add: {name: d, python: dynabrain.modules.basic:Constant, params: {value: [1.0]}}}
          - {at: 6ms, connect: [d.y, g.u]}
          - {at: 7ms, connect: [d.y, g.u]}
          - {at: 8ms, set: {g.u: [3.0]}}
          - {at: 9ms, place: {bb: [1, 0, 1]}, no_collision: [aa], make_joint: [aa, bb]}
          - {at: 10ms, make_joint: [aa, bb]}
          - {at: 11ms, add: {name: d, python: dynabrain.modules.basic:Constant}}
        """)
    text = "\n".join(found)
    for line, words in ((16, "remove: no module 'c' at this time"), (17, "no connection drives 'g.u' at this time"),
                        (18, "module 'c' has been removed by this time"), (21, "g.u is already driven by d.y"),
                        (22, "g.u is driven by d.y at this time"), (23, "'bb' is frozen at this time"),
                        (23, "no_collision needs at least two bodies"), (24, "the joint 'joint_aa_bb' is made already"),
                        (25, "module name 'd' is already used at this time")):
        assert any(f"s.yaml:{line} " in p and words in p for p in found), f"{line}: {words}\n{text}"
    assert len(found) == 9, text


def test_a_module_parameter_that_is_wrong_leaves_the_module_checkable(tmp_path):
    found = problems_of(tmp_path, SIGNALS.replace("{frequency: 2Hz}", "{frequency: .nan, amplitude: 1e300}") + """
connect:
  - [s.yy, g.u]
""")
    text = "\n".join(found)
    assert "s.yaml:5 [modules[0].params.frequency]" in text and "finite" in text
    assert "s.yaml:5 [modules[0].params.amplitude]" in text and "1e+15" in text
    assert "no output port 'yy'" in text, text  # the module was still made, so its ports are known


def test_overrides_given_to_build_are_checked(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(textwrap.dedent(SIGNALS))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path).build(history=-1, step="banana")
    text = str(err.value)
    assert "[world.history]" in text and "[world.step]" in text and "override" in text


def test_param_convert_refuses_non_finite_values():
    from dynabrain.orchestrator.kernel.errors import UnitError
    from dynabrain.orchestrator.kernel.module import Param

    for value in (float("nan"), float("inf"), "1e400", ".nan"):
        with pytest.raises(UnitError):
            Param("k", 1.0).convert(value)
    with pytest.raises(UnitError):
        Param("g", (0.0, 0.0, -9.81)).convert([0, 0, float("-inf")])
    assert Param("k", 1.0).convert("2.5") == 2.5
    unset = Param("limit", float("nan"))
    assert unset.convert(unset.default) != unset.convert(unset.default)  # a NaN default stays the author's choice


def test_cli_duration_override_names_itself_and_errors_print_as_markup(tmp_path):
    from typer.testing import CliRunner

    from dynabrain.orchestrator.cli import main
    from dynabrain.orchestrator.scenario.runner import RunResult

    path = tmp_path / "s.yaml"
    path.write_text(textwrap.dedent(SIGNALS).replace("10ms", "100ms") + "expect:\n  - {at: 80ms, that: \"s.y < 2\"}\n")
    done = CliRunner().invoke(main.app, ["run", str(path), "-q", "--duration", "20ms"])
    assert done.exit_code == 2 and "outside the run (0 .. 20ms)" in done.output, done.output
    done = CliRunner().invoke(main.app, ["run", str(path), "-q", "--duration", "-1s"])
    assert done.exit_code == 2 and "--duration -1s" in done.output
    with main.console.capture() as captured:
        main._summary(RunResult("s", 1, 0.001, 0.1, 1_000_000, [], error="module 'g' [x] failed"), "none")
    out = captured.get()
    assert "run stopped: module 'g' [x] failed" in out and "[bold red]" not in out


def test_nan_is_set_only_where_an_input_means_unset_by_it(tmp_path):
    head = """
        name: t
        world: {step: 2ms, duration: 20ms, core: mujoco}
        scene:
          - box: {name: aa, size: [0.1, 0.1, 0.1], mass: 1, pos: [0, 0, 0.5]}
        modules:
          - {name: g, python: dynabrain.modules.basic:Gain}
        events:
        """
    path = tmp_path / "ok.yaml"
    unset = "[.nan, .nan, 1, .nan, .nan, .nan]"
    path.write_text(textwrap.dedent(head) + f"  - {{at: 4ms, set: {{core.aa.velocity: {unset}}}}}\n")
    load_scenario(path).build().close()  # a body's velocity starts NaN: NaN there leaves a component alone
    found = problems_of(tmp_path, head + """
          - {at: 4ms, set: {core.aa.velocity: [.inf, 0, 0, 0, 0, 0]}}
          - {at: 6ms, set: {g.u: [.nan]}}
        """)
    assert len(found) == 2 and all("finite" in p for p in found), found


def test_a_huge_exponent_is_refused_at_once_with_its_line(tmp_path):
    """Building the exact value of 1e100000000 would take minutes: the quantity's range is checked first."""
    from dynabrain.orchestrator import ScenarioError, load_scenario

    path = tmp_path / "huge.yaml"
    path.write_text("name: huge\nworld: {step: 2ms, duration: 1s, core: mujoco}\n"
                    "scene:\n  - box: {name: b, size: [0.1, 0.1, 0.1], mass: 1e100000000kg}\n")
    with pytest.raises(ScenarioError) as err:
        load_scenario(path).build()
    assert "huge.yaml:4" in str(err.value) and "out of range" in str(err.value)
