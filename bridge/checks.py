"""What the bridge refuses in the values brains send: the scenario layer's limits (`scenario.limits`),
applied to ``set``, brain inputs (``in/set``, ``in/motion``), ``place`` and ``batch``.

- every number finite (NaN and infinity refused; the protocol's typed fields refuse them already), and
  within the scenario's bounds: ±`MAX_MAGNITUDE` for any value, the physics core's ranges for its
  parameters (`CORE_LIMITS`: ``gravity`` within ±`MAX_GRAVITY` m/s^2 per component, ``friction``,
  ``restitution``, ``substeps``), ±`MAX_LENGTH_M` for positions; a parameter's own checks (its type and
  unit, a core's ``_check_param``) run when the world sets it;
- NaN only where it means "unset": in an input whose start value is NaN (a body's ``velocity``);
- a run-time parameter change is tried first on a fork of the world, one tick: a value with which that
  tick fails (a diverging simulation) is refused, unless the tick fails without it too (`trial_set`).

`check_set` uses only the kernel and `scenario.limits`, so the scenario layer could call it as it is.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dynabrain.orchestrator.kernel.errors import DynabrainError, ModuleError
from dynabrain.orchestrator.kernel.module import Module
from dynabrain.orchestrator.kernel.structure import split_signal
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario.limits import (
    CORE_LIMITS,
    MAX_MAGNITUDE,
    check_magnitudes,
    param_problem,
    short,
)
from dynabrain.orchestrator.scenario.scene import parse_pose


class ValueRefusedError(DynabrainError):
    """A value the bridge does not let a brain set (the ``refused`` error reply)."""


def check_set(world: World, name: str, value: Any) -> str | tuple[Module, str]:
    """Refuse (`ValueRefusedError`) a value ``World.set(name, value)`` would take that is not finite, is
    beyond the scenario's limits, or is not what the parameter takes; returns what `World.settable`
    names (an input's full name, or (module, parameter)). The caller holds the world lock."""
    target = world.settable(name)
    if isinstance(target, tuple):
        module, key = target
        limits = CORE_LIMITS.get(key) if module is world.core else None
        problem = param_problem(module.param_specs()[key], value, limits)
        if problem:
            raise ValueRefusedError(f"{name} = {_shown(value)} refused: {problem}")
        return target
    check_input(world, target, value)
    return target


def check_input(world: World, signal: str, value: Any) -> None:
    """An input's value: numbers within ±`MAX_MAGNITUDE`; NaN only in an input whose start value is NaN
    (where NaN means "unset"). A value that is no array of numbers, or of the wrong shape, is left for
    `World.set` to refuse."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return
    finite = np.isfinite(arr)
    if not finite.all():
        if np.isinf(arr).any() or not _unset_is_nan(world, signal):
            raise ValueRefusedError(f"{signal} = {_shown(value)} refused: every value must be a finite number"
                                    " (NaN only where it means unset, in an input that starts NaN)")
        arr = arr[finite]
    if arr.size and float(np.max(np.abs(arr))) > MAX_MAGNITUDE:
        raise ValueRefusedError(f"{signal} = {_shown(value)} refused: values must be within ±{MAX_MAGNITUDE:g}")


def _unset_is_nan(world: World, signal: str) -> bool:
    """Whether input ``signal`` starts all NaN (NaN there means "unset": a body's ``velocity``)."""
    module, port = split_signal(signal)
    found = next((p for p in world.modules[module].inputs() if p.name == port), None)
    if found is None or found.start is None:  # no start value: it starts at 0
        return False
    try:
        return bool(np.all(np.isnan(np.asarray(found.start, dtype=np.float64))))
    except (TypeError, ValueError):
        return False


def _shown(value: Any) -> str:
    """A value as the brain sent it (an array as a list), cut short."""
    return short(value.tolist() if isinstance(value, np.ndarray) else value)


def check_batch_params(world: World, params: dict[str, Any]) -> None:
    """A ``batch`` call's parameter overrides (a value, or one per branch): finite, within ±`MAX_MAGNITUDE`,
    and a parameter of ``world``'s core within its range (`CORE_LIMITS`), whichever form. Names and types
    are `Batch`'s to check."""
    core = world.core.name if world.core is not None else None
    for name, value in params.items():
        module, _, key = name.partition(".")
        try:
            if module == core and key in CORE_LIMITS and not isinstance(value, str):
                low, high = CORE_LIMITS[key]
                for x in np.ravel(np.asarray(value, dtype=np.float64)):
                    if not low <= x <= high:  # NaN too
                        raise ValueRefusedError(f"{name} must be a finite number within [{low:g}, {high:g}], "
                                                f"got {x:g}")
            else:
                check_magnitudes(value, name)
        except (TypeError, ValueError) as exc:  # UnitError is a ValueError
            raise ValueRefusedError(f"batch: params[{name!r}] refused: {exc}") from None


def check_pose(body: str, pos: list[float], quat: list[float] | None) -> None:
    """A ``place``: a position within ±`MAX_LENGTH_M`, a quaternion that is not zero."""
    try:
        parse_pose(list(pos) if quat is None else {"pos": list(pos), "quat": list(quat)})
    except DynabrainError as exc:
        raise ValueRefusedError(f"place {body!r} refused: {exc}") from None


def trial_set(world: World, name: str, value: Any) -> None:
    """Try ``set(name, value)`` on a fork of ``world``, one tick: when that tick fails and the same tick
    without the change does not, refuse the value (`ValueRefusedError`, naming the failure); the world is
    not changed. A world that cannot fork is not tried (its limits are the only check). The caller holds
    the world lock. Costs a fork and a tick (a few ms for the shipped scenarios)."""
    failure = _next_tick_failure(world, name, value)
    if failure is None or _next_tick_failure(world) is not None:
        return
    raise ValueRefusedError(f"{name} = {_shown(value)} refused: with it the next tick fails ({failure}); "
                            "the world is unchanged")


def _next_tick_failure(world: World, name: str | None = None, value: Any = None) -> ModuleError | None:
    try:
        fork = world.fork(f"{world.name}-trial")
    except DynabrainError:  # a module that cannot fork
        return None
    try:
        if name is not None:
            fork.set(name, value)
        fork.tick()
    except ModuleError as exc:
        return exc
    finally:
        fork.close()
    return None
