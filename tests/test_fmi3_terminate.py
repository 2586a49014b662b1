"""A terminate request on a step that succeeded keeps that step (issue 28, item 5). FMI 3.0's
``terminateSimulation`` comes with the step's status: on an OK step the step stands, as FMI 3.0 and
FMPy have it (FMPy's last row is that step's); the world raises `FMUTerminatedError` at the next tick,
and a state from before the request clears it. The same through the C hot path, two FMUs fused into
one crossing, and an isolated FMU. FMI 2.0 asks with ``fmi2Discard``: that step did not happen and is
rolled back, as before."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.fmu import FMUTerminatedError, make_fmu_module
from dynabrain.orchestrator.kernel.world import World

CONFORMANCE = Path(__file__).resolve().parents[1] / "fmus" / "conformance"
pytestmark = pytest.mark.usefixtures("fmu_cache")

HALT_C = """
#include "fmu_model.h"
int model_init(ModelData *m) { m->y = m->u; return MODEL_OK; }
int model_step(ModelData *m, double h) {
    m->y += h * m->u;
    if (m->time + h >= m->stop_at - 1e-9) fmu_stop(m, "halt at t=%g s", m->time + h);
    return MODEL_OK;
}
"""


def halt_fmu(root: Path) -> Path:
    """Reals only (the C hot path): y integrates u; asks to end at stop_at (10 ms)."""
    folder = root / "halt"
    folder.mkdir(exist_ok=True)
    (folder / "fmu.yaml").write_text("name: halt\nfmi: [3]\nvariables:\n  - {name: u, causality: input}\n"
                                     "  - {name: y, causality: output, depends: []}\n"
                                     "  - {name: stop_at, causality: parameter, start: 0.01}\n")
    (folder / "halt.c").write_text(HALT_C)
    return folder


def stopper(version: int, **kw):
    return make_fmu_module("stopper", f"{CONFORMANCE / 'stop'}@fmi{version}", base_dir=".", params={}, targets=[], **kw)


@pytest.mark.parametrize("isolate", [False, True], ids=["in-process", "isolated"])
def test_fmi3_the_step_that_asks_to_end_stands_and_the_next_tick_ends(isolate):
    with World(step="100ms") as w:
        w.add_module(stopper(3, isolate=isolate))
        w.tick(9)
        w.tick()  # the step to the FMU's t=2 s asks to end: it stands
        assert (w.tick_count, w.get("stopper.steps"), w.get("stopper.t")) == (10, 10.0, 2.0)
        for _ in range(2):  # the end is asked again at every tick after
            with pytest.raises(FMUTerminatedError, match=r"asked to end the simulation in its step from t=1\.9 s "
                                                         r"\(that step stands\)") as err:
                w.tick()
            assert err.value.tick == 10 and w.tick_count == 10 and w.get("stopper.steps") == 10.0
        w.backtick(3)  # a state from before the request: it steps again, and asks again at the same step
        w.tick(3)
        assert (w.tick_count, w.get("stopper.steps")) == (10, 10.0)
        with pytest.raises(FMUTerminatedError):
            w.tick()


def test_fmi2_asks_with_a_discard_and_that_step_is_rolled_back():
    with World(step="100ms") as w:
        w.add_module(stopper(2))
        with pytest.raises(FMUTerminatedError) as err:
            w.tick(20)
        assert err.value.tick == 9 and w.tick_count == 9 and w.get("stopper.steps") == 9.0


def test_the_hot_path_and_a_fused_pair_keep_the_step_too(tmp_path):
    folder = halt_fmu(tmp_path)
    with World(step="1ms") as w:
        for name in ("a", "b"):
            w.add_module(make_fmu_module(name, str(folder), base_dir=".", params={}, targets=[]))
        w.connect("a.y", "b.u")
        w.set("a.u", 1.0)
        w.tick(10)  # both ask in their tenth step; both steps stand
        assert w.modules["a"]._fused is not None  # the pair steps in one crossing into C
        assert w.tick_count == 10 and np.isclose(w.get("a.y"), 0.01) and w.get("b.y") > 0
        y = (w.get("a.y"), w.get("b.y"))
        with pytest.raises(FMUTerminatedError, match=r"halt at t=0\.01 s"):
            w.tick()
        assert (w.get("a.y"), w.get("b.y")) == y and w.tick_count == 10
        w.backtick(2)  # the request comes again at the same step
        w.tick(2)
        assert w.tick_count == 10 and (w.get("a.y"), w.get("b.y")) == y
