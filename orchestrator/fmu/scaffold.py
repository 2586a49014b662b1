"""``dynabrain fmu new NAME``: a C FMU folder that builds and passes `check_fmu` as generated.

The example is a first-order lag, ``T y' = k u - y``, integrated exactly over each step: one input,
one output, two tunable parameters and a state of its own. Edit fmu.yaml and NAME.c from there.
"""

from __future__ import annotations

from pathlib import Path

from .errors import FMUError
from .spec import IDENT, RESERVED

FMU_YAML = """\
# {name}: declared here, computed in {name}.c. `dynabrain fmu build .` makes the .fmu;
# `dynabrain fmu check .` builds and checks it. See fmus/README.md for the fields.
name: {name}
description: a first-order lag, T y' = k u - y
fmi: [2, 3]
step: 0.001
variables:
  - {{name: u, causality: input, description: input}}
  - {{name: y, causality: output, depends: [], description: "output (the lag's state)"}}
  - {{name: k, causality: parameter, variability: tunable, start: 1.0, description: gain}}
  - {{name: T, causality: parameter, variability: tunable, start: 0.1, unit: s, description: time constant}}
"""

MODEL_C = """\
/* {name}: a first-order lag, T y' = k u - y, integrated exactly over each step.
 * ModelData (generated from fmu.yaml into model_data.h) holds every variable; the glue saves,
 * restores and serializes it for you. Return MODEL_OK, or MODEL_DISCARD / MODEL_ERROR /
 * MODEL_FATAL after saying why with fmu_log(). */
#include <math.h>

#include "fmu_model.h"

int model_init(ModelData *m) {{
    if (!(m->T > 0.0)) {{
        fmu_log(m, MODEL_ERROR, "T must be > 0, got %g", m->T);
        return MODEL_ERROR;
    }}
    m->y = m->k * m->u;
    return MODEL_OK;
}}

int model_step(ModelData *m, double h) {{
    if (!(m->T > 0.0)) {{
        fmu_log(m, MODEL_ERROR, "T must be > 0, got %g", m->T);
        return MODEL_ERROR;
    }}
    double a = 1.0 - exp(-h / m->T);
    m->y += a * (m->k * m->u - m->y);
    return MODEL_OK;
}}
"""


def new_fmu(name: str, parent: str | Path = ".") -> Path:
    """Create ``parent/name`` with fmu.yaml and ``name.c``; returns the folder."""
    if not IDENT.match(name):
        raise FMUError(f"FMU name {name!r} must be a C identifier (letters, digits, _; not starting with a digit)")
    if name in RESERVED:
        raise FMUError(f"FMU name {name!r} is reserved: the generated C code uses {', '.join(sorted(RESERVED))} "
                       "itself (the model's state is m, its step h); choose another name")
    folder = Path(parent) / name
    if folder.exists() and any(folder.iterdir()):
        raise FMUError(f"{folder} exists and is not empty")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "fmu.yaml").write_text(FMU_YAML.format(name=name), encoding="utf-8")
    (folder / f"{name}.c").write_text(MODEL_C.format(name=name), encoding="utf-8")
    return folder
