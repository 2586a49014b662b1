"""Running a scenario to its end: ticks, expectations at their times, a result to print.

A module may ask to end the simulation (an FMU's terminate request raises `EndRequestedError`): the
run ends cleanly at the tick where it asked (that tick's step is rolled back, as the world does for
any failed tick, so the world stands at the start of it), and that is a normal end, not an error:
`RunResult.ended` says which module asked, at which tick and time, and why. The expectations are
checked over the ticks run: one due by then is checked as usual (also at the last tick); a
``during`` window cut short passes if it held over the ticks it got, and says so; one due after the
end is not reached and fails, saying where the run ended. So a run that ends on a terminate request
is ``ok`` when every expectation it reached holds and none was left unreached.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from ..kernel.errors import EndRequestedError
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
    ended: str | None = None
    """Why the run ended before its duration when a module asked to end it (a terminate request): the
    module, the tick and time, and its reason; None when the run went its whole duration or failed."""
    ended_by: str | None = None
    """The module that asked to end the run, or None."""

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
    error = ended = ended_by = None
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
    except EndRequestedError as exc:  # a normal end: the tick that asked has been rolled back
        ended_by = exc.module
        ended = (f"module {exc.module!r} asked to end the simulation at tick {world.tick_count} "
                 f"(t={world.time:.6g} s): {exc.cause}")
    except Exception as exc:  # a failed tick has been rolled back; report it with the results
        error = str(exc)
    wall = time.perf_counter() - wall0
    if ended is not None:
        _at_the_end(world, reader, expectations, ended_by)
    for exp in expectations:
        if exp.passed is None:
            exp.passed, exp.detail = False, exp.detail or "not reached"
    result = RunResult(scenario.model.name, world.tick_count, world.time, wall, world.dt_ns, expectations, error,
                       ended, ended_by)
    if own:
        world.close()
    return result


def _at_the_end(world: World, reader: object, expectations: list[Expectation], module: str | None) -> None:
    """After a terminate request: check what is due at the tick the run ended at, pass a ``during``
    window that held over the ticks it got, and say where the run ended for one not reached."""
    tick = world.tick_count
    who = f"module {module!r} asked to end the simulation"
    for exp in expectations:
        if exp.passed is None and exp.start <= tick <= exp.end:
            exp.check(world, reader)
        if exp.passed is None and exp.start <= tick:
            exp.passed, exp.detail = True, f"held up to tick {tick}, where {who}"
        elif exp.passed is None:
            exp.passed, exp.detail = False, f"not reached: the run ended at tick {tick} (t={world.time:.6g} s): {who}"


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
