"""FMU modules next to each other in the schedule step in one call into the C helper
(`orchestrator.fmu.fused`). Real FMUs built from ``fmus/``; each result is compared bit for bit with
the same world on the plain tick, which steps every module on its own."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.fmu import FMUCallError, make_fmu_module
from dynabrain.orchestrator.fmu.build import build_fmu
from dynabrain.orchestrator.fmu.fused import GroupState
from dynabrain.orchestrator.kernel.errors import ModuleError
from dynabrain.orchestrator.kernel.world import World

FMUS = Path(__file__).resolve().parents[1] / "fmus"
FAULTY_C = """
#include "fmu_model.h"
int model_init(ModelData *m) { m->y = m->x; return MODEL_OK; }
int model_step(ModelData *m, double h) {
    if (m->u > 2) { fmu_log(m, MODEL_ERROR, "u=%g is out of range", m->u); return MODEL_ERROR; }
    m->x += m->u * h;
    m->y = m->x;
    return MODEL_OK;
}
"""

pytestmark = pytest.mark.usefixtures("fmu_cache")


@pytest.fixture(scope="module", params=[2, 3], ids=["fmi2", "fmi3"])
def filt(request) -> Path:
    return build_fmu(FMUS / "sensor_filter", request.param)


@pytest.fixture(scope="module")
def faulty(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("src") / "integrate"
    folder.mkdir()
    (folder / "fmu.yaml").write_text("name: integrate\nfmi: [2]\nvariables:\n  - {name: u, causality: input}\n"
                                     "  - {name: y, causality: output}\n  - {name: x, causality: local}\n")
    (folder / "integrate.c").write_text(FAULTY_C)
    return build_fmu(folder, 2)


def chain(fmus: list[tuple[str, Path]], *, compiled: bool, **params) -> World:
    """FMUs in a chain (each ``y`` into the next ``u``), noise on so each has a state that matters."""
    world = World("chain", step="2ms", history=200, compiled=compiled)
    for name, ref in fmus:
        world.add_module(make_fmu_module(name, str(ref), base_dir=".", params=params, targets=[]))
    for (a, _), (b, _) in itertools.pairwise(fmus):
        world.connect(f"{a}.y", f"{b}.u")
    return world


def bus(world: World) -> bytes:
    return world.bus.tobytes()


def test_a_chain_steps_as_one_and_matches_the_separate_steps(filt):
    names = [(f"f{i}", filt) for i in range(4)]
    fused, plain = (chain(names, compiled=c, sigma=0.01) for c in (True, False))
    assert "fused_f0_f3(t_ns" in fused.structure.compiled.source  # one call steps the four
    for w in (fused, plain):
        w.set("f0.u", [1.0, 2.0, 3.0])
        w.tick(40)
    assert isinstance(fused.modules["f2"].get_state(), GroupState)
    assert bus(fused) == bus(plain)
    for w in (fused, plain):  # back across ticks, an input changed, forward again
        w.backtick(15)
        w.set("f0.u", [0.5, -1.0, 2.0])
        w.tick(25)
    assert bus(fused) == bus(plain)
    snap = fused.snapshot()
    fused.tick(10)
    after = bus(fused)
    fused.restore(snap)
    fused.tick(10)
    assert bus(fused) == after
    for w in (fused, plain):
        w.close()


def test_fused_states_export_import_and_fork(filt):
    names = [(f"f{i}", filt) for i in range(3)]
    world = chain(names, compiled=True, sigma=0.02)
    world.set("f0.u", [1.0, 0.0, -1.0])
    world.tick(30)
    data = world.export_state()
    other = chain(names, compiled=True, sigma=0.02)
    other.import_state(data)
    twin = world.fork()
    for w in (world, other, twin):
        w.tick(20)
    assert bus(world) == bus(other) == bus(twin)
    assert np.all(np.isfinite(world.get("f2.y")))
    for w in (world, other, twin):
        w.close()


def test_a_member_that_fails_is_named_and_the_tick_rolls_back(faulty):
    names = [("a", faulty), ("b", faulty), ("c", faulty)]
    fused, plain = (chain(names, compiled=c) for c in (True, False))
    for w in (fused, plain):
        w.set("a.u", 1.0)
        w.tick(900)  # b's input, a's x, grows past 2 at about 2 s
    assert bus(fused) == bus(plain)
    assert fused.tick_count == 900
    for w in (fused, plain):
        with pytest.raises((FMUCallError, ModuleError), match=r"b.*out of range") as exc:
            w.tick(1000)
        assert "'b'" in str(exc.value) or "module b" in str(exc.value)
    assert fused.tick_count == plain.tick_count
    assert bus(fused) == bus(plain)
    for w in (fused, plain):  # the world goes on from where it stopped, after a step back
        w.backtick(100)
        w.set("a.u", -1.0)
        w.tick(50)
    assert bus(fused) == bus(plain)
    for w in (fused, plain):
        w.close()


def test_removing_a_member_keeps_the_others_states(filt):
    names = [(f"f{i}", filt) for i in range(3)]
    fused, plain = (chain(names, compiled=c, sigma=0.01) for c in (True, False))
    for w in (fused, plain):
        w.set("f0.u", [1.0, 1.0, 1.0])
        w.tick(20)
        w.remove_module("f2")
        w.tick(10)
        w.backtick(5)  # within the new structure: states of the two left, saved by the old group
        w.tick(10)
    assert fused.get("f1.y").tobytes() == plain.get("f1.y").tobytes()
    for w in (fused, plain):
        w.close()
