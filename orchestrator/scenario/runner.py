"""Running a scenario to its end: ticks, expectations at their times, a result to print."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from ..kernel.world import World
from .expect import Expectation, namespace_for
from .model import Scenario


@dataclass
class RunResult:
    scenario: str
    ticks: int
    sim_time: float
    wall_time: float
    dt_ns: int
    expectations: list[Expectation] = field(default_factory=list)
    error: str | None = None

    @property
    def realtime_factor(self) -> float:
        return self.sim_time / self.wall_time if self.wall_time > 0 else float("inf")

    @property
    def ok(self) -> bool:
        return self.error is None and all(e.passed for e in self.expectations)


def run_scenario(scenario: Scenario, world: World | None = None, *,
                 progress: Callable[[int, int], None] | None = None, realtime: bool | float | None = None,
                 chunk: int = 50) -> RunResult:
    """Run ``scenario`` for its duration and check its expectations. The world is closed at the end
    unless one was passed in."""
    own = world is None
    world = world if world is not None else scenario.build()
    expectations = list(scenario.expectations)
    total = scenario.duration_ns // world.dt_ns
    reader = namespace_for(world)
    factor = scenario.model.world.realtime if realtime is None else realtime
    factor = 1.0 if factor is True else (float(factor) if factor else None)
    wall0 = time.perf_counter()
    error = None
    try:
        stop = world.tick_count
        while True:
            if stop > world.tick_count:
                _advance(world, stop - world.tick_count, factor, wall0)
            tick = world.tick_count
            for exp in expectations:
                if exp.start <= tick <= exp.end and exp.passed is not False:
                    exp.check(world, reader)
            if progress is not None:
                progress(tick, total)
            if tick >= total:
                break
            stop = _next_stop(tick, total, chunk, expectations)
    except Exception as exc:  # a failed tick has been rolled back; report it with the results
        error = str(exc)
    wall = time.perf_counter() - wall0
    for exp in expectations:
        if exp.passed is None:
            exp.passed, exp.detail = False, exp.detail or "not reached"
    result = RunResult(scenario.model.name, world.tick_count, world.time, wall, world.dt_ns, expectations, error)
    if own:
        world.close()
    return result


def _next_stop(tick: int, total: int, chunk: int, expectations: list[Expectation]) -> int:
    """The next tick to stop at: the end of this chunk of ``chunk`` ticks, the end of the run, or the
    next tick an expectation is due (every tick of a ``during`` window)."""
    stop = min(total, (tick // chunk + 1) * chunk)
    for exp in expectations:
        if exp.passed is not False and exp.end > tick:
            stop = min(stop, exp.start if exp.start > tick else tick + 1)
    return stop


def _advance(world: World, n: int, factor: float | None, wall0: float) -> None:
    if factor is None:
        world.tick(n)
        return
    for _ in range(n):
        world.tick()
        ahead = wall0 + world.time / factor - time.perf_counter()
        if ahead > 0:
            time.sleep(ahead)
