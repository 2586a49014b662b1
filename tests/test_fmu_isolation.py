"""Isolation (``isolate: true``): an FMU in its own process steps exactly like one in ours, and one
that segfaults or aborts is reported with module, call and tick while the world rolls back and goes
on (when the FMU's state cannot be kept, the FMU is restarted from scratch, and the user told so).
The MCAP log stays readable."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.Log_pb2 import Log
from mcap.reader import make_reader

from dynabrain.orchestrator.fmu import FMUCallError, FMUCrashError, FMUTimeoutError, make_fmu_module
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.errors import ScenarioError
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.scenario.model import load_scenario

FMUS = Path(__file__).resolve().parents[1] / "fmus"

CRASHY_VARS = """\
  - {name: u, causality: input}
  - {name: y, causality: output}
  - {name: x, causality: local}
  - {name: how, type: integer, causality: parameter, start: 0, description: "0 segv, 1 abort, 2 fatal, 3 spin"}
  - {name: at_init, type: boolean, causality: parameter, start: false}
"""
CRASHY_C = """
#include <stdio.h>
#include <stdlib.h>
#include "fmu_model.h"

static int crash(const ModelData *m) {
    fprintf(stderr, "crashy: giving up at t=%g\\n", m->time);
    fflush(stderr);
    if (m->how == 2) { fmu_log(m, MODEL_FATAL, "beyond repair"); return MODEL_FATAL; }
    if (m->how == 3) { volatile int spin = 1; while (spin) {} }
    if (m->how == 1) abort();
    volatile int *p = 0;
    *p = 42;
    return MODEL_OK;
}
int model_init(ModelData *m) { if (m->at_init) return crash(m); m->y = m->x; return MODEL_OK; }
int model_step(ModelData *m, double h) {
    if (m->u > 0.5) return crash(m);
    m->x += m->u * h;
    m->y = m->x;
    return MODEL_OK;
}
"""


pytestmark = pytest.mark.usefixtures("fmu_cache")  # FMUs built here go to a cache of this module's own


def crashy_folder(root: Path, serialize: bool = True) -> Path:
    folder = root / ("crashy" if serialize else "crashy_plain")
    if not folder.exists():
        folder.mkdir(parents=True)
        caps = "" if serialize else "capabilities: {get_set_state: false, serialize: false}\n"
        (folder / "fmu.yaml").write_text(f"name: crashy\nfmi: [2, 3]\n{caps}variables:\n{CRASHY_VARS}")
        (folder / "crashy.c").write_text(CRASHY_C)
    return folder


@pytest.fixture(scope="module")
def crashy(tmp_path_factory) -> Path:
    return crashy_folder(tmp_path_factory.mktemp("src"))


def module(ref, name: str, isolate: bool = True, **params):
    return make_fmu_module(name, str(ref), base_dir=".", params=params, targets=[], isolate=isolate)


@pytest.mark.parametrize(("version", "room"), [(2, None), (3, None), (2, 16)], ids=["fmi2", "fmi3", "state-by-pipe"])
def test_isolated_fmu_steps_bit_for_bit_like_one_in_process(version, room, monkeypatch):
    if room is not None:  # a state longer than the step file holds crosses the pipe (`worker.last_state`)
        monkeypatch.setattr("dynabrain.orchestrator.fmu.isolate.STATE_BYTES", room)
    worlds = []
    for isolate in (False, True):
        w = World(step="1ms")
        w.add_module(module(f"{FMUS / 'sensor_filter'}@fmi{version}", "s", isolate, sigma=0.1, seed=3))
        w.set("s.u", [0.1, 0.2, 0.3])
        worlds.append(w)
    try:
        for _ in range(20):
            for w in worlds:
                w.tick()
            assert np.array_equal(worlds[0].snapshot().bus, worlds[1].snapshot().bus)
        for w in worlds:
            w.backtick(8)
            w.set("s.sigma", 0.5)
            w.tick(4)
        assert np.array_equal(worlds[0].snapshot().bus, worlds[1].snapshot().bus)
    finally:
        for w in worlds:
            w.close()


def test_isolated_module_passes_check_module():
    check_module(module(FMUS / "servo", "servo"), step="2ms", ticks=10).assert_ok()


@pytest.mark.parametrize(("how", "signal", "version"), [(0, "SIGSEGV", 2), (1, "SIGABRT", 2), (0, "SIGSEGV", 3)])
def test_crash_is_reported_rolled_back_and_the_world_goes_on(crashy, how, signal, version):
    ref = World(step="1ms")
    w = World(step="1ms")
    try:
        ref.add_module(module(f"{crashy}@fmi{version}", "c", isolate=False, how=how))
        w.add_module(module(f"{crashy}@fmi{version}", "c", how=how))
        for world in (ref, w):
            world.set("c.u", 0.25)
            world.tick(10)
        pid = w.modules["c"].pid
        w.set("c.u", 1.0)
        with pytest.raises(FMUCrashError) as err:
            w.tick()
        e = err.value
        assert (e.module, e.tick, e.call) == ("c", 10, f"fmi{version}DoStep")
        assert signal in str(e) and "giving up at t=0.01" in str(e) and "crashy" in str(e)
        assert w.tick_count == 10 and w.get("c.y") == ref.get("c.y")
        w.set("c.u", 0.25)
        w.tick(10)  # a new process, restored to tick 10, takes over
        ref.tick(10)
        assert w.modules["c"].pid not in (None, pid)
        assert w.get("c.y") == ref.get("c.y")
        w.backtick(15)  # history from before the crash still restores
        ref.backtick(15)
        assert w.get("c.y") == ref.get("c.y")
    finally:
        ref.close()
        w.close()


def test_fatal_status_in_isolation_restarts_the_fmu_from_the_last_good_tick(crashy):
    with World(step="1ms") as w:
        w.add_module(module(crashy, "c", how=2))
        w.set("c.u", 0.5)
        w.tick(4)
        y = w.get("c.y")
        w.set("c.u", 0.9)
        with pytest.raises(FMUCallError, match=r"fmi2Fatal.*beyond repair"):
            w.tick()
        assert w.modules["c"].pid is None  # the corrupted process is gone
        w.set("c.u", 0.5)
        w.tick()
        assert w.get("c.y") == pytest.approx(y + 0.0005)


def test_crash_of_an_fmu_without_serializable_state_restarts_it_from_scratch(tmp_path, caplog):
    m = module(crashy_folder(tmp_path, serialize=False), "c")
    assert not m.CAPABILITIES.can_rollback
    with World(step="1ms") as w:
        w.add_module(m)
        w.set("c.u", 0.25)
        w.tick(3)
        assert w.get("c.y") == pytest.approx(0.00075)
        w.set("c.u", 1.0)
        with pytest.raises(FMUCrashError, match=r"SIGSEGV.*its state is lost \(.*crashy.* cannot serialize it\): "
                                                r"the next step restarts it from scratch"):
            w.tick()
        assert w.tick_count == 3 and m.pid is None
        w.set("c.u", 0.25)
        with caplog.at_level("WARNING", logger="dynabrain.fmu"):
            w.tick()  # a new process, initialized at t=3 ms: the 0.75 ms of integration before are lost
        assert w.get("c.y") == pytest.approx(0.00025) and m.pid is not None
        assert len(m.restarts) == 1 and "restarted from scratch at t=0.003 s" in m.restarts[0]
        assert "its state before was lost" in caplog.text
    assert m.pid is None


def test_a_hung_fmu_is_killed_after_its_call_timeout_and_the_world_goes_on(crashy):
    hung = make_fmu_module("c", str(crashy), base_dir=".", params={"how": 3}, targets=[], isolate=True,
                           call_timeout=2.0)  # every other call answers in well under that, even on a busy machine
    with World(step="1ms") as w:
        w.add_module(hung)
        w.set("c.u", 0.25)
        w.tick(5)
        y, pid = w.get("c.y"), hung.pid
        w.set("c.u", 1.0)  # the FMU spins for ever in this step
        with pytest.raises(FMUTimeoutError) as err:
            w.tick()
        e = err.value
        assert isinstance(e, FMUCrashError) and (e.module, e.tick, e.call) == ("c", 5, "fmi2DoStep")
        assert "did not answer within 2 s" in str(e) and "SIGKILL" in str(e)
        assert w.tick_count == 5 and w.get("c.y") == y and hung.pid != pid
        with pytest.raises(ProcessLookupError):  # the hung process is gone (the rollback to tick 5 may have
            os.kill(pid, 0)                      # started another, to step again from the keyframe at tick 4)
        w.set("c.u", 0.25)
        w.tick(2)  # a new process, from the last good tick
        assert hung.pid not in (None, pid) and w.get("c.y") == pytest.approx(y + 2 * 0.25e-3)


def test_call_timeout_is_checked_in_a_scenario(crashy, tmp_path):
    def scenario(extra: str) -> Path:
        path = tmp_path / "s.yaml"
        path.write_text(f"name: s\nworld: {{step: 1ms, core: null}}\nmodules:\n  - name: c\n    fmu: {crashy}\n"
                        f"{extra}")
        return path

    world = load_scenario(scenario("    isolate: true\n    call_timeout: 2500ms\n")).build()
    try:
        assert world.modules["c"].call_timeout == 2.5
        assert world.modules["c"].scenario_spec()["call_timeout"] == 2.5
    finally:
        world.close()
    for extra, message in (("    call_timeout: 1s\n", "isolate: true"),
                           ("    isolate: true\n    call_timeout: -1s\n", "positive"),
                           ("    isolate: true\n    call_timeout: soon\n", "soon")):
        with pytest.raises(ScenarioError, match=rf"s.yaml:\d+ \[modules\[0\].call_timeout\]: .*{message}"):
            load_scenario(scenario(extra)).build()


def test_crash_during_initialization_refuses_the_module(crashy):
    with World(step="1ms") as w:
        with pytest.raises(FMUCrashError, match=r"fmi2ExitInitializationMode.*SIGSEGV"):
            w.add_module(module(crashy, "c", at_init=True))
        assert w.modules == {}
        w.tick()


def test_the_mcap_log_stays_readable_after_a_crash(crashy, tmp_path):
    path = tmp_path / "run.mcap"
    with World(step="1ms") as w:
        w.add_module(module(crashy, "c"))
        logger = McapLogger(path).attach(w)
        w.set("c.u", 0.25)
        w.tick(20)
        w.set("c.u", 1.0)
        with pytest.raises(FMUCrashError):
            w.tick()
        w.set("c.u", 0.25)
        w.tick(20)
        logger.close()
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        assert reader.get_summary() is not None
        events = [json.loads(Log.FromString(m.data).message)  # foxglove.Log, the event as JSON in its message
                  for _s, ch, m in reader.iter_messages() if ch.topic == "/events"]
    errors = [e for e in events if e["kind"] == "error"]
    assert len(errors) == 1 and errors[0]["tick"] == 20 and "SIGSEGV" in errors[0]["detail"]["message"]
    assert errors[0]["detail"]["module"] == "c"
