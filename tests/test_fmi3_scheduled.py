"""FMI 3.0 scheduled execution (issue 28, item 2), with fmus/conformance/scheduled: an FMU with that
interface alone (no co-simulation, as the Reference FMU Clocks has it) built here. No steps: at each
tick the module activates the model partition of every input clock that ticks there
(``fmi3ActivateModelPartition``): a periodic clock (10 ms), a triggered one (its port), a countdown
the triggered one starts (3 ms), a tunable one (its period taken at its next tick); an output clock
the model ticks in a partition is read after it. The tick pattern is checked tick by tick; rollback
and an isolated FMU replay it bit for bit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.fmu import make_fmu_module
from dynabrain.orchestrator.kernel.world import World

SCHEDULED = Path(__file__).resolve().parents[1] / "fmus" / "conformance" / "scheduled"
pytestmark = pytest.mark.usefixtures("fmu_cache")
COLUMNS = ("ticks", "total", "resets", "laters", "t_later", "beats", "t_beat", "third", "thirds")


def run(world: World, n: int, reset_at: tuple[int, ...] = ()) -> list[tuple[float, ...]]:
    """``n`` ticks, the triggered clock set for the ticks in ``reset_at``; each tick's outputs."""
    rows = []
    for _ in range(n):
        world.set("s.reset", 1.0 if world.tick_count + 1 in reset_at else 0.0)
        world.tick()
        rows.append(tuple(float(world.get(f"s.{c}")) for c in COLUMNS))
    return rows


def scheduled(**kw):
    return make_fmu_module("s", str(SCHEDULED), base_dir=".", params={}, targets=[], **kw)


def test_the_partitions_run_at_their_clocks_ticks():
    m = scheduled()
    assert m.info.scheduled and m.info.version == 3 and "FMI 3.0" in m.info.label
    assert [p.name for p in m.inputs()] == ["gain", "reset"]
    with World(step="1ms") as w:
        w.add_module(m)
        w.set("s.gain", 0.5)
        rows = run(w, 40, reset_at=(15,))
    at = {k + 1: dict(zip(COLUMNS, r, strict=True)) for k, r in enumerate(rows)}
    # tick (10 ms): at 0 (the start), 10, 20, 30, 40 ms; the reset at 15 ms counts it from 0 again
    assert [at[k]["ticks"] for k in (9, 10, 19, 20, 30, 39, 40)] == [1, 2, 2, 1, 2, 2, 3]
    assert at[40]["total"] == 1.0 + 4 * 0.5  # the tick at the start saw gain's start value (1), the others 0.5
    assert [at[k]["resets"] for k in (14, 15, 40)] == [0, 1, 1]
    # later: a countdown of 3 ms the reset started, once
    assert (at[17]["laters"], at[18]["laters"], at[18]["t_later"], at[40]["laters"]) == (0, 1, 0.018, 1)
    # beat (tunable, 25 ms): at the start and at 25 ms
    assert (at[24]["beats"], at[25]["beats"], at[25]["t_beat"]) == (1, 2, 0.025)
    # third: the output clock the model ticks at every third tick (40 ms) says 1 at that tick only
    assert [k for k in at if at[k]["third"]] == [40] and at[40]["thirds"] == 1


def test_a_tunable_clock_takes_its_new_period_at_its_next_tick():
    with World(step="1ms") as w:
        w.add_module(scheduled())
        run(w, 5)
        w.set("s.period", 0.01)  # taken at the beat at 25 ms; then every 10 ms
        rows = run(w, 50)
    beats = [r[COLUMNS.index("t_beat")] for r in rows]
    assert sorted(set(beats)) == [0.0, 0.025, 0.035, 0.045, 0.055]


def test_rollback_and_isolation_replay_the_pattern_bit_for_bit():
    with World(step="1ms") as w, World(step="1ms") as v:
        w.add_module(scheduled())
        v.add_module(scheduled(isolate=True))
        first = run(w, 45, reset_at=(7, 31))
        assert run(v, 45, reset_at=(7, 31)) == first
        w.backtick(30)
        assert run(w, 30, reset_at=(31,)) == first[15:]
        assert np.array_equal(w.snapshot().bus, v.snapshot().bus)
