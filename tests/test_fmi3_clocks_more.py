"""FMI 3.0 input clocks whose interval the FMU gives while it runs (fmus/conformance/aperiodic, built
here): a tunable clock (periodic; a new period taken at an event counts from there), a changing clock
(its next interval read at each tick), a countdown clock (ticks once when the interval it was given
runs out). They tick where the FMU says, and their schedule is state: rollback, fork and isolation
replay them bit for bit. An interval that falls between two steps is refused naming clock and time."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.fmu import FMUCallError, FMUError, load_fmu_info, make_fmu_module
from dynabrain.orchestrator.fmu.build import build_fmu, package_fmu
from dynabrain.orchestrator.kernel.world import World

ROOT = Path(__file__).resolve().parents[1]
CLOCKS = ("beat", "chirp", "alarm")

pytestmark = pytest.mark.usefixtures("fmu_cache")


def world(isolate: bool = False, period: str = "1ms", **params) -> World:
    w = World(step="1ms")
    w.add_module(make_fmu_module("a", "fmus/conformance/aperiodic", base_dir=str(ROOT), params=params, targets=[],
                                 isolate=isolate), period=period)
    return w


def run(w: World, ticks: int, retune: dict[int, float] | None = None) -> tuple[dict[str, list[int]], list]:
    """Tick ``ticks`` times (setting ``period`` before the ticks in ``retune``); each clock's ticks (ms,
    from its clocked outputs) and the bus after every tick."""
    seen: dict[str, list[int]] = {c: [] for c in CLOCKS}
    count = {c: w.get(f"a.{c}s") for c in CLOCKS}
    rows = []
    for _ in range(ticks):
        if retune and w.tick_count in retune:
            w.set("a.period", retune[w.tick_count])
        w.tick()
        for c in CLOCKS:
            if w.get(f"a.{c}s") != count[c]:
                count[c] = w.get(f"a.{c}s")
                seen[c].append(round(w.get(f"a.t_{c}") * 1000))
        rows.append(w.snapshot().bus.copy())
    return seen, rows


def test_tunable_changing_and_countdown_clocks_tick_where_the_fmu_says():
    info = load_fmu_info("fmus/conformance/aperiodic", base_dir=str(ROOT))
    assert [(c.name, c.variability, c.dynamic, c.on_bus) for c in info.clocks] == [
        ("beat", "tunable", True, False), ("chirp", "changing", True, False), ("alarm", "countdown", True, False)]
    with world() as w:
        assert (w.get("a.beats"), w.get("a.chirps"), w.get("a.alarms")) == (1, 0, 0)  # beat ticks at the start
        seen, _ = run(w, 150, retune={50: 0.03})
    assert seen == {"beat": [20, 40, 60, 90, 120, 150],  # 30 ms from the beat at 60 ms that took the new period
                    "chirp": [10, 30, 60, 70, 90, 120, 130, 150],  # 10, 20, 30, 10, 20, 30, ... ms apart
                    "alarm": [65, 125]}  # 5 ms after every third chirp (60, 120 ms)


def test_their_schedule_rolls_back_forks_and_runs_isolated_bit_for_bit():
    retune = {50: 0.03}
    results = []
    for isolate in (False, True):
        with world(isolate) as w:
            _, first = run(w, 62, retune)  # at 62 ms: the alarm counts down to 65, the new period is taken
            _, rest = run(w, 80)
            w.backtick(80)
            assert np.array_equal(w.snapshot().bus, first[-1])
            seen, again = run(w, 80)
            assert all(np.array_equal(a, b) for a, b in zip(rest, again, strict=True))
            assert seen["alarm"] == [65, 125] and seen["beat"] == [90, 120]  # not the ticks of before the rollback
            w.backtick(30)
            fork = w.fork()
            _, forked = run(fork, 30)
            _, own = run(w, 30)
            assert all(np.array_equal(a, b) for a, b in zip(forked, own, strict=True))
            fork.close()
            results.append(first + rest)
    assert all(np.array_equal(a, b) for a, b in zip(*results, strict=True))


def test_an_interval_between_two_steps_is_refused_naming_the_clock_and_the_time():
    with world(period="2ms") as w:  # steps of 2 ms: 25 ms (the tunable period) falls between two
        w.tick(20)
        w.set("a.period", 0.025)
        with pytest.raises(FMUCallError, match=r"module 'a': fmi3GetIntervalDecimal\(\) at tick 38 failed: .*"
                                               r"clock 'beat' \(tunable\) was given the interval 0.025 s at "
                                               r"t=0.04 s, not a positive whole number of the module's periods "
                                               r"\(0.002 s\)"):
            w.tick(20)
        assert w.tick_count == 38  # rolled back to the start of the module's step that reached the beat at 40 ms
    with World(step="1ms") as w, pytest.raises(FMUCallError, match=r"clock 'chirp' \(changing\) was given the "
                                                                   r"interval 0.01 s at t=0 s, not a whole number "
                                                                   r"of the module's periods \(0.004 s\)"):
        w.add_module(make_fmu_module("a", "fmus/conformance/aperiodic", base_dir=str(ROOT), params={}, targets=[]),
                     period="4ms")


def test_a_clock_that_gets_no_interval_from_the_fmu_is_refused_naming_it(tmp_path):
    """A tunable clock whose FMU says fmi3IntervalNotYetKnown after initialization has no period."""
    built = build_fmu(ROOT / "fmus" / "conformance" / "sampled_pi", 3)
    with zipfile.ZipFile(built) as zf:
        xml = zf.read("modelDescription.xml").decode()
        lib = next(n for n in zf.namelist() if n.startswith("binaries/"))
        (tmp_path / "sampled_pi.so").write_bytes(zf.read(lib))
    xml = xml.replace('intervalVariability="triggered"', 'intervalVariability="tunable"')
    bad = package_fmu(tmp_path / "bad.fmu", xml, {str(Path(lib).parent): tmp_path / "sampled_pi.so"})
    with World(step="1ms") as w, pytest.raises(FMUError, match=r"bad.fmu .*clock 'reset' \(tunable\) has no interval "
                                                               r"after initialization \(fmi3GetIntervalDecimal: "
                                                               r"fmi3IntervalNotYetKnown\)"):
        w.add_module(make_fmu_module("pi", str(bad), base_dir=".", params={}, targets=[]))


def test_a_clock_port_wired_to_a_continuous_output_is_refused_at_build_naming_both_ends(tmp_path):
    """A clock input (a triggered input clock: a port of unit clock) takes only a clock output; a clocked
    *variable* fed by a continuous output is sampled at its clock's ticks (FMI 3.0's sampled data)."""
    from dynabrain.orchestrator.kernel.errors import ScenarioError
    from dynabrain.orchestrator.scenario.model import load_scenario

    path = tmp_path / "clk.yaml"
    path.write_text(f"name: clk\nworld: {{step: 1ms, duration: 10ms, core: null}}\nmodules:\n"
                    f"  - {{name: plant, fmu: '{ROOT / 'fmus/conformance/plant'}@fmi3'}}\n"
                    f"  - {{name: pi, fmu: '{ROOT / 'fmus/conformance/sampled_pi'}'}}\n"
                    "connect:\n  - [plant.y, pi.reset]\n  - [pi.alarm, plant.u]\n")
    with pytest.raises(ScenarioError) as bad:
        load_scenario(path).build()
    text = str(bad.value)
    assert "clk.yaml:7 [connect[0]]: connection plant.y -> pi.reset: unit mismatch, plant.y is in '1', pi.reset " \
           "in 'clock'" in text
    assert "clk.yaml:8 [connect[1]]: connection pi.alarm -> plant.u: unit mismatch, pi.alarm is in 'clock'" in text


# -- early return (fmus/conformance/crossing) ----------------------------------------------------------
def crossing(isolate: bool = False) -> World:
    w = World(step="10ms")
    w.add_module(make_fmu_module("c", "fmus/conformance/crossing", base_dir=str(ROOT), params={}, targets=[],
                                 isolate=isolate))
    return w


def rows_of(w: World, ticks: int) -> list[tuple[float, ...]]:
    out = []
    for _ in range(ticks):
        w.tick()
        out.append(tuple(float(w.get(f"c.{k}")) for k in ("x", "pieces", "since", "turns", "t_turn", "turn")))
    return out


def test_an_fmu_that_returns_early_has_its_event_handled_there_and_steps_on_from_it():
    """x rises at 1/s to 25 mm and falls back: the turn at 25 ms falls inside the step from 20 ms, which
    ends there (an early return); the master handles the event at 25 ms (the output clock and its
    clocked outputs) and steps on from 25 ms to 30 ms. The turn at 50 ms is a step's end: one piece."""
    with crossing() as w:
        got = rows_of(w, 8)
    assert [r[1] for r in got] == [1, 2, 4, 5, 6, 7, 8, 10]  # DoStep calls: two for the steps with a turn inside
    assert [round(r[2], 12) for r in got] == [0.0, 0.01, 0.025, 0.03, 0.04, 0.05, 0.06, 0.075]  # the last began
    assert [r[3] for r in got] == [0, 0, 1, 1, 2, 2, 2, 3] and [r[5] for r in got] == [0, 0, 1, 0, 1, 0, 0, 1]
    assert [round(r[4], 12) for r in got[2:]] == [0.025, 0.025, 0.05, 0.05, 0.05, 0.075]  # each turn's own time
    assert [round(r[0], 12) for r in got] == [0.01, 0.02, 0.02, 0.01, 0.0, 0.01, 0.02, 0.02]  # the triangle


def test_early_returns_roll_back_fork_and_run_isolated_bit_for_bit():
    results = []
    for isolate in (False, True):
        with crossing(isolate) as w:
            first = rows_of(w, 12)
            bus = w.snapshot().bus.copy()
            w.backtick(9)  # back over three turns
            again = rows_of(w, 9)
            assert again == first[3:] and np.array_equal(w.snapshot().bus, bus)
            fork = w.fork()
            assert rows_of(fork, 7) == rows_of(w, 7)
            fork.close()
            results.append(first)
    assert results[0] == results[1]
