"""The pieces of the receding-horizon controller (`brain.mpc`): its decision variables (`Control`), what a cost
function sees (`Futures`), a replan's result (`Replan`), how the controller kept up (`MpcStats`), its
error, and the checks of its options.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError
from ..kernel.units import parse_quantity

METHODS = ("sampling", "cem", "mppi")
AGGREGATES = ("mean", "worst", "cvar")
PLAYER = "dynabrain.modules.playback:PlanPlayer"


class MpcError(DynabrainError):
    """A controller that cannot be made (its controls, parameters or signals) or a replan that failed."""


@dataclass(frozen=True)
class Control:
    """One decision variable of the plan: the input ``ports`` it drives (all with the same values),
    its bounds ``low`` .. ``high``, and the spread of its samples ``noise`` (a standard deviation in the
    ports' unit; default a quarter of the range)."""

    ports: Sequence[str]
    low: float
    high: float
    noise: float | None = None


@dataclass
class Futures:
    """What a cost function sees: ``signals[name]`` of shape ``(futures, ticks, *shape)`` over the
    horizon (after the delay's ticks), ``controls[name]`` the values each future played ``(futures,
    ticks)``, ``dt`` (s). A cost returns one number a future (lower is better)."""

    signals: dict[str, np.ndarray]
    controls: dict[str, np.ndarray]
    dt: float

    def __getitem__(self, name: str) -> np.ndarray:
        return self.signals[name]

    def last(self, name: str) -> np.ndarray:
        """A signal's value at the end of the horizon, ``(futures, *shape)``."""
        return self.signals[name][:, -1]


@dataclass
class Replan:
    """One replan: the new plan's knots ``(knots, channels)`` and per-tick ``values`` ``(ticks,
    channels)``, its ``cost`` (the best sample's), every sample's ``costs``, the best sample's recorded
    ``signals`` (its future, over the horizon), the tick it was planned from and at, the delay compensated
    (ticks) and the wall time it took."""

    knots: np.ndarray
    values: np.ndarray
    cost: float
    costs: np.ndarray
    signals: dict[str, np.ndarray]
    tick: int
    delay_ticks: int
    wall_s: float
    failed: int = 0


@dataclass
class MpcStats:
    """How the controller kept up: replans made, their mean and worst wall time, how many came later
    than the delay they planned for and by how much at worst (s), the ticks it ran for."""

    replans: int = 0
    wall_s: list[float] = field(default_factory=list)
    late: int = 0
    worst_late_s: float = 0.0
    ticks: int = 0
    costs: list[float] = field(default_factory=list)

    @property
    def replans_per_s(self) -> float:
        total = sum(self.wall_s)
        return self.replans / total if total > 0 else float("inf")

    def summary(self) -> str:
        if not self.wall_s:
            return "no replan yet"
        mean_ms, worst_ms = np.mean(self.wall_s) * 1e3, max(self.wall_s) * 1e3
        return (f"{self.replans} replans, {self.replans_per_s:.1f}/s of planning (mean {mean_ms:.0f} ms, worst "
                f"{worst_ms:.0f} ms); {self.late} came late (worst by {self.worst_late_s * 1e3:.0f} ms)")


def _first(ports: Sequence[str] | str) -> str:
    return ports if isinstance(ports, str) else ports[0]


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float, np.number)) and not isinstance(x, bool) and math.isfinite(float(x))


def _ticks(dt_s: float, value: int | float | str, what: str) -> int:
    """A tick count from ticks (an int) or a duration (``"1s"``, or seconds as a float)."""
    if isinstance(value, bool):
        raise MpcError(f"mpc: {what} is {value!r}; give ticks or a duration")
    if isinstance(value, (int, np.integer)):
        ticks = int(value)
    else:
        try:
            seconds = parse_quantity(value, "time") if isinstance(value, str) else float(value)
        except (DynabrainError, TypeError, ValueError):
            raise MpcError(f"mpc: {what} is {value!r}; give ticks or a duration ('1s', or seconds)") from None
        ticks = round(seconds / dt_s)
    if ticks < 1:
        raise MpcError(f"mpc: {what} is {value!r}: at least one tick")
    return ticks


def _state_tick(state: bytes) -> int:
    from ..kernel import portable

    return int(portable.decode(state).tick)


def _check_options(knots: int, samples: int, method: str, iterations: int, elite: float, temperature: float,
                   draws: int, aggregate: str, cvar: float, horizon: int) -> None:
    for name, value, least in (("knots", knots, 1), ("samples", samples, 2), ("iterations", iterations, 1),
                               ("draws", draws, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise MpcError(f"mpc: {name} is {value!r}; a whole number of at least {least}")
    if knots > horizon:
        raise MpcError(f"mpc: {knots} knots over a horizon of {horizon} ticks; at most one a tick")
    if method not in METHODS:
        raise MpcError(f"mpc: method {method!r} is unknown; methods: {', '.join(METHODS)}")
    if aggregate not in AGGREGATES:
        raise MpcError(f"mpc: aggregate {aggregate!r} is unknown; one of {', '.join(AGGREGATES)}")
    for name, value in (("elite", elite), ("cvar", cvar)):
        if not (_finite(value) and 0 < value <= 1):
            raise MpcError(f"mpc: {name} is {value!r}; a fraction in (0, 1]")
    if not (_finite(temperature) and temperature > 0):
        raise MpcError(f"mpc: temperature is {temperature!r}; a number above 0")
