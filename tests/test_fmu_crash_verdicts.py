"""Crashing FMUs get verdicts (issue 28, item 5). `dynabrain fmu check` runs its probes in a child
process: an FMU that segfaults in fmi2DeSerializeFMUstate (its glue's deserialization wrapped, at link
time, by a function that writes through a null pointer) is reported as crashed in that call during the
fork probe, and one that segfaults in a step during the run; the command exits 1 with the report,
not 139. An isolated FMU's crash message shows only what its process wrote during the failing call,
not the lines of earlier steps."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.fmu import FMUCrashError, make_fmu_module
from dynabrain.orchestrator.fmu.checkproc import check_fmu_apart
from dynabrain.orchestrator.kernel.world import World

pytestmark = pytest.mark.usefixtures("fmu_cache")

VARS = """\
  - {name: u, causality: input}
  - {name: y, causality: output, depends: []}
  - {name: x, causality: local}
"""
CHATTY_C = """
#include <stdio.h>
#include <stddef.h>
#include "fmu_model.h"

int model_init(ModelData *m) { m->y = m->x; return MODEL_OK; }
int model_step(ModelData *m, double h) {
    fprintf(stderr, "chatty: step from t=%g\\n", m->time);
    if (m->u > 0.5 || m->time > 0.0095) { /* a large input, or the step from t=10 ms */
        fprintf(stderr, "chatty: giving up\\n");
        fflush(stderr);
        volatile int *p = NULL;
        *p = 42;
    }
    m->x += m->u * h;
    m->y = m->x;
    return MODEL_OK;
}
"""
BROKEN_FORK_C = """
#include <stdio.h>
#include <stddef.h>
#include "fmu_model.h"

int model_init(ModelData *m) { m->y = m->x; return MODEL_OK; }
int model_step(ModelData *m, double h) { m->x += m->u * h; m->y = m->x; return MODEL_OK; }

/* the glue's state deserialization, wrapped at link time (-Wl,--wrap): it crashes */
int __wrap_core_deserialize(void *inst, const unsigned char *in, size_t size, void **state) {
    (void)inst, (void)in, (void)state;
    fprintf(stderr, "broken: reading a state of %zu bytes\\n", size);
    fflush(stderr);
    volatile int *p = NULL;
    *p = 42;
    return 3;
}
"""


def write_fmu(root: Path, name: str, c_source: str, extra: str = "") -> Path:
    folder = root / name
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "fmu.yaml").write_text(f"name: {name}\nfmi: [2]\n{extra}variables:\n{VARS}")
    (folder / f"{name}.c").write_text(c_source)
    return folder


def test_fmu_check_gives_a_verdict_for_a_crash_in_the_fork_probe(tmp_path):
    folder = write_fmu(tmp_path, "broken", BROKEN_FORK_C, "cflags: ['-Wl,--wrap=core_deserialize']\n")
    out = CliRunner().invoke(app, ["fmu", "check", str(folder), "--ticks", "20"])
    text = " ".join(out.output.split())
    assert out.exit_code == 1, text  # a failed check, not a dead command (139)
    assert "crashed in fmi2DeSerializeFMUstate during the fork probe (killed by SIGSEGV)" in text
    assert "broken: reading a state of" in text and "FAILED" in text


def test_a_crash_during_the_run_names_the_step(tmp_path):
    folder = write_fmu(tmp_path, "chatty", CHATTY_C)
    report, output = check_fmu_apart(str(folder), ticks=20)  # its 11th step crashes
    assert not report.ok and report.info is not None and report.info.model_name == "chatty"
    [problem] = report.problems
    assert problem.startswith("the FMU crashed in fmi2DoStep during the run of 20 ticks (killed by SIGSEGV)"), problem
    assert "chatty: giving up" in problem and "chatty: giving up" in output


def test_an_isolated_crash_shows_only_the_output_of_the_failing_call(tmp_path):
    folder = write_fmu(tmp_path, "chatty", CHATTY_C)
    with World(step="1ms") as w:
        w.add_module(make_fmu_module("c", str(folder), base_dir=".", params={}, targets=[], isolate=True))
        w.set("c.u", 0.25)
        w.tick(5)
        w.set("c.u", 1.0)
        with pytest.raises(FMUCrashError) as err:
            w.tick()
    message = str(err.value)
    assert "SIGSEGV" in message and "its output in this call: chatty: step from t=0.005 | chatty: giving up" in message
    assert "t=0.004" not in message  # the steps before wrote too: not shown
