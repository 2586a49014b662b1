"""MuJoCo's physics options (``<option>``: timestep, integrator, cone, solver, iterations ...) for the core.

- A primitive scene gets the core's defaults (`DEFAULTS`): the ``implicitfast`` integrator, elliptic
  cones, the Newton solver (see `mujoco.core`);
- a model file keeps its own options: what its ``<option>`` elements say (`declared`: the file's and
  those of the files it includes), its timestep included (`own_timestep`: the core steps MuJoCo at it,
  `substeps_for`); where it says nothing, the core's defaults (and MuJoCo's for the rest);
- the scene's ``options`` (``scene: {model: ..., options: {integrator: rk4, iterations: 50}}`` in a
  scenario, `SceneSpec.options`) override either, one by one; a name MuJoCo's ``mjOption`` does not
  have, or a value that does not fit it, is refused naming the option (`option_problem`);
- whatever a scene says, MuJoCo's automatic reset on bad numbers stays off (a divergence raises
  `PhysicsDivergedError`) and so does sleeping (its state is not in what the core saves); ``gravity`` is
  the core's parameter (``core: {gravity: ...}``), and the flags (``disableflags`` ...) are not options
  here.
"""

from __future__ import annotations

import math
import os
from typing import Any

import mujoco

from dynabrain.orchestrator.kernel.suggest import did_you_mean

ENUMS = {
    "integrator": (mujoco.mjtIntegrator, "mjINT_"),
    "cone": (mujoco.mjtCone, "mjCONE_"),
    "solver": (mujoco.mjtSolver, "mjSOL_"),
    "jacobian": (mujoco.mjtJacobian, "mjJAC_"),
}
"""Options that name one of MuJoCo's enum values (case-insensitive: ``rk4``, ``implicitfast``, ``newton``)."""
NOT_OPTIONS = {
    "gravity": "gravity is the core's parameter: core: {gravity: [0, 0, -9.81]}",
    "disableflags": "MuJoCo's flags are not scene options here",
    "enableflags": "MuJoCo's flags are not scene options here",
    "disableactuator": "MuJoCo's flags are not scene options here",
}
DEFAULTS = {"integrator": mujoco.mjtIntegrator.mjINT_IMPLICITFAST, "cone": mujoco.mjtCone.mjCONE_ELLIPTIC,
            "solver": mujoco.mjtSolver.mjSOL_NEWTON}
"""The core's options where a scene does not say (MuJoCo's own defaults are Euler, pyramidal, Newton)."""
MAX_COUNT = 10_000
"""The largest whole-number option (iterations and the like)."""
MAX_MAGNITUDE = 1e15
"""The largest number an option takes (the scenario's bound on numbers)."""
MAX_SUBSTEPS = 10_000
"""The most MuJoCo steps a timestep may make of one world step (the scenario's bound on ``substeps``)."""
MAX_INCLUDES = 256
"""The most files `declared` reads for one model (an include that includes itself stops there)."""


def names() -> list[str]:
    """The options a scene may set: every field of MuJoCo's ``mjOption`` but those of `NOT_OPTIONS`."""
    opt = mujoco.MjSpec().option
    return sorted(a for a in dir(opt) if not a.startswith("_") and a not in NOT_OPTIONS)


def option_problem(key: Any, value: Any) -> str | None:
    """What is wrong with option ``key`` = ``value`` (None: nothing). A number is SI (``timestep`` in s)."""
    known = names()
    if key in NOT_OPTIONS:
        return f"option {key!r}: {NOT_OPTIONS[key]}"
    if key not in known:
        return (f"MuJoCo has no option {key!r}" + did_you_mean(str(key), known) + f"; options: {', '.join(known)}")
    if key in ENUMS:
        members = _members(key)
        return None if str(value).lower() in members else (
            f"option {key}: unknown value {value!r} (one of {', '.join(members)})")
    now = getattr(mujoco.MjSpec().option, key)
    if hasattr(now, "__len__"):
        ok = (isinstance(value, list | tuple) and len(value) == len(now)
              and all(_finite(x) for x in value))
        return None if ok else f"option {key}: {len(now)} numbers (at most {MAX_MAGNITUDE:g}), got {value!r}"
    whole = isinstance(value, int) and not isinstance(value, bool)
    if isinstance(now, int) and not (whole and 0 <= value <= MAX_COUNT):
        return f"option {key}: a whole number from 0 to {MAX_COUNT}, got {value!r}"
    if not _finite(value) or value < 0 or (key == "timestep" and value <= 0):
        return f"option {key}: a finite number {'above' if key == 'timestep' else 'from'} 0, got {value!r}"
    return None


def apply(spec: mujoco.MjSpec, options: dict, *, own: frozenset[str] = frozenset()) -> None:
    """Give ``spec`` its options: the core's defaults (`DEFAULTS`) where the model does not set its own
    (``own``: `declared`), then ``options`` (checked: `option_problem`; raises ValueError naming the first
    bad one)."""
    opt = spec.option
    for key, value in DEFAULTS.items():
        if key not in own:
            setattr(opt, key, value)
    opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
    opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_SLEEP)  # sleep state is not in mjSTATE_INTEGRATION
    for key, value in options.items():
        problem = option_problem(key, value)
        if problem:
            raise ValueError(problem)
        if key in ENUMS:
            setattr(opt, key, _members(key)[str(value).lower()])
        elif isinstance(getattr(opt, key), int):
            setattr(opt, key, int(value))
        elif hasattr(getattr(opt, key), "__len__"):
            setattr(opt, key, [float(x) for x in value])
        else:
            setattr(opt, key, float(value))


def own_timestep(spec: mujoco.MjSpec | None, options: dict, own: frozenset[str]) -> float | None:
    """The timestep (s) a scene asks for: its options', or a model file's own (``spec``, when its
    ``<option>`` sets one: ``own``); None: the core's substeps rule."""
    if "timestep" in options:
        return float(options["timestep"])
    return float(spec.option.timestep) if spec is not None and "timestep" in own else None


def declared(path: str) -> frozenset[str]:
    """The options a model file's ``<option>`` elements set (their attributes), in the file and in the
    files it includes (MuJoCo reads an include's path from the model file's folder); nothing for a file
    that is not MJCF (a URDF) or that does not parse as XML here (MuJoCo reads it, and says what is wrong)."""
    from lxml import etree

    parser = etree.XMLParser(resolve_entities=False, no_network=True, remove_comments=True)
    folder, todo, seen, out = os.path.dirname(path), [path], set(), set()
    while todo and len(seen) < MAX_INCLUDES:
        file = todo.pop()
        if file in seen:
            continue
        seen.add(file)
        try:
            root = etree.parse(file, parser).getroot()
        except (OSError, etree.XMLSyntaxError):
            continue
        out |= {key for element in root.iter("option") for key in element.attrib}
        todo += [os.path.join(folder, inc.get("file", "")) for inc in root.iter("include") if inc.get("file")]
    return frozenset(out)


def substeps_for(period_s: float, timestep_s: float) -> int:
    """MuJoCo steps per world step for a timestep: the step divided by it when it divides the step, else
    the fewest steps whose length is not above it (one when the world's step is shorter). Raises
    ValueError above `MAX_SUBSTEPS`."""
    n = max(1, math.ceil(period_s / timestep_s - 1e-9))
    if n > MAX_SUBSTEPS:
        raise ValueError(f"a timestep of {timestep_s:g} s makes {n} MuJoCo steps of the world's step of "
                         f"{period_s:g} s; at most {MAX_SUBSTEPS}")
    return n


def _members(key: str) -> dict[str, Any]:
    enum, prefix = ENUMS[key]
    return {n[len(prefix):].lower(): v for n, v in enum.__members__.items()}


def _finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and abs(x) <= MAX_MAGNITUDE
