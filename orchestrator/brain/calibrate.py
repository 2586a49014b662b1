"""Absorbing the difference: the physical parameters that explain what really happened.

The paper's closing wish: "functions that absorb the difference between the predicted situation and
the real, and customize the simulator on site". The brain ran a motion on the real world (or a world
served over the bridge, or the robot link) and recorded what it observed; its own world predicted
something else. `calibrate` finds the values of some run-time parameters (a body's friction or
restitution, a servo gain, gravity: ranges the user gives) for which the brain's world, replaying the
same inputs from the same start, records what was observed. A body's own friction, restitution and
mass (``core.<body>.mass``) are such parameters. Each generation of candidates is one
batch of futures (`Batch`); the search is CMA-ES (the ``cma`` package) over the ranges, scaled to the
unit box.

    fit = calibrate(brain, observed={"core.box.pos": seen}, params={"core.box.friction": (0.1, 1.2)},
                    start=start_state, inputs={"core.box.velocity": pushes})
    fit.estimates          # {"core.box.friction": 0.352}
    fit.residual_before, fit.residual_after, fit.identifiable
    fit.apply(brain)       # the brain's world takes the estimates; then replan

The residual is the root mean square over the observed signals of the difference, each signal scaled
by its own spread in the observation (so metres and radians weigh alike). A parameter is identifiable
when moving it by a tenth of its range from the estimate raises the residual measurably; one that does
not (the residual is flat along it: the motion never exercised it) is reported as such, its estimate
None and the world's value left alone, never a made-up number.

Bad input is refused before anything runs, naming it: a parameter or signal the world lacks, an
observation of the wrong shape or length, a range that is not two finite numbers.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cma
import numpy as np

from ..kernel.errors import DynabrainError
from ..kernel.world import World
from .batch import Batch

FLAT = 0.01
"""A parameter is identifiable when a tenth of its range moves the residual by more than this fraction
of the residual before calibration (or of the observation's scale, when it was already exact)."""
PROBE = 0.1
"""How far (a fraction of the range) each parameter is moved from the estimate to test that."""


class CalibrationError(DynabrainError):
    """A calibration that cannot run: its parameters, observation or options."""


@dataclass
class Calibration:
    """The outcome: ``estimates`` (parameter -> value, None where not identifiable), ``identifiable``,
    the residual with the world's own values (``residual_before``) and with the estimates
    (``residual_after``), how much each parameter's probe raised the residual (``sensitivity``, as a
    fraction), the futures simulated (``evaluations``) and the wall time."""

    estimates: dict[str, float | None]
    identifiable: dict[str, bool]
    residual_before: float
    residual_after: float
    sensitivity: dict[str, float]
    best: dict[str, float]
    evaluations: int
    wall_s: float

    def apply(self, world: World) -> dict[str, float]:
        """Set the identifiable estimates on ``world``; returns what was set."""
        done = {}
        for name, value in self.estimates.items():
            if value is not None:
                world.set(name, value)
                done[name] = value
        return done

    def describe(self) -> str:
        parts = []
        for name, value in self.estimates.items():
            parts.append(f"{name} = {value:.4g}" if value is not None else
                         f"{name}: not identifiable (the residual is flat along it; kept as it was)")
        return (f"residual {self.residual_before:.4g} -> {self.residual_after:.4g} after {self.evaluations} futures "
                f"in {self.wall_s:.1f} s; " + "; ".join(parts))


def calibrate(world: World, observed: Mapping[str, Any], params: Mapping[str, tuple[float, float]], *,
              start: bytes | None = None, inputs: Mapping[str, Any] | None = None, budget: int = 240,
              popsize: int | None = None, batch: Batch | None = None, backend: str = "auto",
              seed: int = 1) -> Calibration:
    """Fit ``params`` (name -> (low, high)) so that ``world``, run from ``start`` (default: its state now)
    with ``inputs`` (port -> per-tick values, as `World.run` takes them), records ``observed`` (signal
    -> ``(ticks, *shape)``, row k after tick k+1). ``budget``: futures to simulate at most; ``popsize``:
    candidates a generation (CMA-ES's default for the dimension). The world itself does not change."""
    t0 = time.perf_counter()
    obs, ticks = _observation(world, observed)
    names, low, high = _ranges(world, params)
    drive = _inputs(world, inputs or {}, ticks)
    state = start if start is not None else world.export_state()
    scale = {n: float(np.std(v)) or float(np.max(np.abs(v))) or 1.0 for n, v in obs.items()}
    own = batch is None
    batch = batch or Batch(world, backend=backend)
    evaluations = 0

    def residuals(values: np.ndarray) -> np.ndarray:
        nonlocal evaluations
        values = np.atleast_2d(values)
        result = batch.run(ticks, branches=len(values), starts=state, keep_states=False, record=list(obs),
                           inputs=drive, params={n: values[:, k].tolist() for k, n in enumerate(names)})
        evaluations += len(values)
        out = np.zeros(len(values))
        for name, seen in obs.items():
            diff = (result.signals[name] - seen[None]) / scale[name]
            out += np.mean(diff.reshape(len(values), -1) ** 2, axis=1)
        out = np.sqrt(out / len(obs))
        ok = np.array([s.ok for s in result.status])
        return np.where(ok & np.isfinite(out), out, np.inf)

    try:
        before = _current(world, names)
        r_before = float(residuals(np.array([before]))[0]) if before is not None else math.nan
        best_x, best_r = _search(residuals, low, high, budget, popsize, seed)
        probes = []
        for k in range(len(names)):
            for sign in (-1.0, 1.0):
                x = best_x.copy()
                x[k] = np.clip(x[k] + sign * PROBE * (high[k] - low[k]), low[k], high[k])
                probes.append(x)
        raised = residuals(np.array(probes)).reshape(len(names), 2)
    finally:
        if own:
            batch.close()
    ref = r_before if math.isfinite(r_before) and r_before > best_r else 1.0
    sensitivity = {n: float((np.mean(raised[k]) - best_r) / ref) for k, n in enumerate(names)}
    identifiable = {n: sensitivity[n] > FLAT for n in names}
    return Calibration({n: float(best_x[k]) if identifiable[n] else None for k, n in enumerate(names)},
                       identifiable, r_before, float(best_r), sensitivity,
                       {n: float(best_x[k]) for k, n in enumerate(names)}, evaluations, time.perf_counter() - t0)


def _search(residuals: Any, low: np.ndarray, high: np.ndarray, budget: int, popsize: int | None,
            seed: int) -> tuple[np.ndarray, float]:
    """CMA-ES over the unit box (one generation a batch); the best point seen and its residual."""
    span = high - low
    opts: dict[str, Any] = {"bounds": [0.0, 1.0], "seed": seed, "verbose": -9, "maxfevals": budget,
                            "tolfun": 1e-9, "tolx": 1e-5}
    if popsize is not None:
        opts["popsize"] = popsize
    if len(low) == 1:  # cma needs two dimensions: a second that nothing reads
        span, low = np.append(span, 1.0), np.append(low, 0.0)
    es = cma.CMAEvolutionStrategy([0.5] * len(low), 0.3, opts)
    best_x, best_r = None, math.inf
    dims = len(high)
    while not es.stop():
        xs = np.array(es.ask())
        r = residuals(low[:dims] + xs[:, :dims] * span[:dims])
        es.tell(list(xs), [float(v) if math.isfinite(v) else 1e30 for v in r])
        b = int(np.argmin(r))
        if r[b] < best_r:
            best_r, best_x = float(r[b]), low[:dims] + xs[b, :dims] * span[:dims]
    if best_x is None:
        raise CalibrationError("calibrate: no candidate ran to the end (every future failed)")
    return best_x, best_r


def _observation(world: World, observed: Mapping[str, Any]) -> tuple[dict[str, np.ndarray], int]:
    if not observed:
        raise CalibrationError("calibrate: give at least one observed signal")
    obs: dict[str, np.ndarray] = {}
    ticks = None
    for name, values in observed.items():
        try:
            shape = world.signal_shape(name)
        except DynabrainError as exc:
            raise CalibrationError(f"calibrate: observed[{name!r}]: {exc}") from None
        arr = np.asarray(values, dtype=np.float64)
        if arr.ndim != len(shape) + 1 or arr.shape[1:] != shape:
            raise CalibrationError(f"calibrate: observed[{name!r}] has shape {arr.shape}; a signal of shape {shape} "
                                   f"observed over T ticks is (T, {', '.join(map(str, shape))})".replace(", )", ")"))
        if ticks is not None and len(arr) != ticks:
            raise CalibrationError(f"calibrate: observed[{name!r}] covers {len(arr)} ticks where the others cover "
                                   f"{ticks}")
        if not np.all(np.isfinite(arr)):
            raise CalibrationError(f"calibrate: observed[{name!r}] holds values that are not finite")
        ticks = len(arr)
        obs[name] = arr
    if not ticks:
        raise CalibrationError("calibrate: the observation covers no tick")
    return obs, int(ticks)


def _ranges(world: World, params: Mapping[str, tuple[float, float]]) -> tuple[list[str], np.ndarray, np.ndarray]:
    if not params:
        raise CalibrationError("calibrate: give at least one parameter and its range")
    names, low, high = [], [], []
    for name, bounds in params.items():
        if world.material_target(name) is None:
            try:
                target = world.settable(name)
            except DynabrainError as exc:
                raise CalibrationError(f"calibrate: params[{name!r}]: {exc}") from None
            if isinstance(target, str):
                raise CalibrationError(f"calibrate: params[{name!r}] is an input port; calibrate run-time parameters")
            module, key = target
            if not module.param_specs()[key].runtime:
                raise CalibrationError(f"calibrate: params[{name!r}] cannot be changed at run time")
        ok = isinstance(bounds, (tuple, list)) and len(bounds) == 2 and all(
            isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b) for b in bounds)
        if not ok or not bounds[0] < bounds[1]:
            raise CalibrationError(f"calibrate: params[{name!r}] is {bounds!r}; give (low, high) with low < high")
        names.append(name)
        low.append(float(bounds[0]))
        high.append(float(bounds[1]))
    return names, np.array(low), np.array(high)


def _inputs(world: World, inputs: Mapping[str, Any], ticks: int) -> dict[str, np.ndarray]:
    out = {}
    for name, values in inputs.items():
        try:
            shape = world.signal_shape(name)
        except DynabrainError as exc:
            raise CalibrationError(f"calibrate: inputs[{name!r}]: {exc}") from None
        arr = np.asarray(values, dtype=np.float64)
        if arr.shape == shape:
            arr = np.broadcast_to(arr, (ticks, *shape))
        if arr.shape != (ticks, *shape):
            raise CalibrationError(f"calibrate: inputs[{name!r}] has shape {arr.shape}; it needs {(ticks, *shape)} "
                                   "(one row a tick of the observation)")
        out[name] = arr
    return out


def _current(world: World, names: list[str]) -> list[float] | None:
    """The world's own values of the parameters (None when one cannot be read)."""
    values = []
    for name in names:
        material = world.material_target(name)
        try:
            if material is not None:
                body, key = material
                value = getattr(world.core.material(body), key)
                if value is None and key == "mass":  # the model's own (a MuJoCo core's view of its model)
                    value = world.core.mj.model.body(body).mass[0]
                elif value is None:  # the body takes the core's coefficient
                    value = world.core.params[key]
            else:
                value = world.get(name)
            values.append(float(value))
        except (DynabrainError, TypeError, ValueError, KeyError, AttributeError):
            return None
    return values
