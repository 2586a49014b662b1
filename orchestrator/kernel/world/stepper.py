"""The stepper: a world's ticks (as Drake's Simulator advances a Context), the scenario's events due at
them, and a failed tick undone.

One tick (n -> n+1), the failure policy of each phase in brackets:

1. if the world was edited since the state of tick n was saved, save it again (edits are inputs);
2. fire the scenario's events due at tick n  [an error rolls back to tick n and is raised];
3. copy delayed connections; step each due module in schedule order, copying its direct inputs
   first  [an exception rolls back to tick n and is raised as `ModuleError`]; check that the outputs
   are finite  [a NaN or an infinity rolls back to tick n: `NonFiniteOutputError`, see `finite`];
4. tick = n+1; save the state in history (with keyframes, ``keyframe_every``: at every k-th tick and
   after events, else the tick's number only); tell observers.

Step 3 is one generated call (`CompiledTick.bind`), and step 4's history entry another
(`compiled.state_saver`); a rollback to a tick history holds by number restores the keyframe before
it and steps the ticks between again (`Timeline.replay`).
"""

from __future__ import annotations

import numpy as np

from ..compiled import CompiledTick, PlainTick
from ..errors import DynabrainError, ModuleError
from ..units import format_duration, parse_duration_ns
from .context import Context, ScheduledAction
from .timeline import Timeline


class Stepper:
    """Steps one world (see the module docstring)."""

    def __init__(self, ctx: Context, timeline: Timeline):
        self.ctx = ctx
        self.timeline = timeline

    def steps(self, count: int) -> None:
        """``count`` ticks, each read from the context again (an event or an observer may edit the world
        between two). The hot path: what is not needed at every tick is in `fire_events` and
        `Timeline.make_saver`."""
        ctx, timeline = self.ctx, self.timeline
        scheduled, dt_ns = ctx.scheduled, ctx.dt_ns
        for _ in range(count):
            if ctx.dirty:
                ctx.history.replace_top(timeline.capture())
                ctx.dirty = False
            n = ctx.tick
            keyframe = False
            if n in scheduled:  # (events may change the structure, and with it `run_tick`)
                keyframe = self.fire_events(n, scheduled[n])
            try:
                ctx.run_tick(n, n * dt_ns)  # the steps and the finite-output check (`CompiledTick.bind`)
            except Exception as exc:  # roll back to the last good tick, then report
                where = self.runner().failed_module(exc.__traceback__) or "?"  # the traceback says which module
                raise self.rollback_failed_tick(n, where, exc) from exc
            except BaseException:  # KeyboardInterrupt and the like: roll back, re-raise as is
                timeline.back_to(0)
                ctx.dirty = False
                raise
            ctx.tick = n + 1
            if ctx.saver_of is not ctx.structure:
                timeline.make_saver(ctx.structure)
            if keyframe:  # a whole state after events: stepping again from a keyframe never runs them twice
                ctx.history.push(timeline.capture())
            else:
                ctx.record(n + 1)  # history's entry, as `capture` makes it
            ctx.dirty = False
            if ctx.observers:
                for obs in ctx.observers:
                    obs.on_tick(ctx.view)

    def fire_events(self, n: int, events: list[tuple[str, ScheduledAction]]) -> bool:
        """Run the scenario's actions due at tick ``n`` (True when there were some); one that fails rolls
        the tick back and raises."""
        if not events:
            return False
        ctx, current = self.ctx, "?"
        ctx.source = "scenario"
        try:
            for label, action in events:
                current = label
                action(ctx.world)
        except Exception as exc:
            ctx.source = "api"
            raise self.rollback_failed_tick(n, f"event {current}", exc) from exc
        except BaseException:
            ctx.source = "api"
            self.timeline.back_to(0)
            ctx.dirty = False
            raise
        ctx.source = "api"
        return True

    def runner(self) -> CompiledTick | PlainTick:
        """The tick the world runs (``ctx.run_tick`` is it, bound to the bus)."""
        return self.ctx.structure.compiled if self.ctx.compiled else self.ctx.structure.plain

    def rollback_failed_tick(self, n: int, where: str, exc: Exception) -> ModuleError:
        ctx = self.ctx
        self.timeline.back_to(0)
        ctx.dirty = False
        if isinstance(exc, ModuleError):
            err = exc if exc.tick is not None else exc.at_tick(n)
        elif where.startswith("event"):
            err = ModuleError(where, "apply", n, exc)
        else:
            err = ModuleError(where, "step", n, exc)
        ctx.error = err
        ctx.emit("error", message=str(err), module=err.module, failed_tick=n)
        ctx.rolled_back(n)
        return err

    def ticks_of(self, n: int | float | str, call: str) -> int:
        """A tick count from a count or a duration (`World.ticks_of`)."""
        if isinstance(n, bool) or not isinstance(n, (int, float, str, np.integer, np.floating)):
            raise DynabrainError(f"{call}: expected a tick count or a duration ('1s', or seconds as a float), "
                                 f"got {n!r}")
        if isinstance(n, (int, np.integer)):
            if n < 0:
                raise DynabrainError(f"{call}: {n} ticks; a count is 0 or more (backtick goes back)")
            return int(n)
        dt_ns = self.ctx.dt_ns
        try:
            ns = parse_duration_ns(n if isinstance(n, str) else float(n), allow_frequency=False)
        except (DynabrainError, ValueError, TypeError, OverflowError) as exc:
            raise DynabrainError(f"{call}: {n!r} is not a duration: {exc}") from None
        if ns < 0 or ns % dt_ns:
            raise DynabrainError(f"{call}: {n!r} is not a whole number of the world's {format_duration(dt_ns)} "
                                 "steps (and not negative)")
        return ns // dt_ns

    # -- the scenario's events --------------------------------------------------------------------------
    def at(self, t: int | float | str, label: str, action: ScheduledAction) -> int:
        """Schedule ``action(world)`` at the tick at time ``t``; returns the tick (`World.at`)."""
        ctx = self.ctx
        ns = t if isinstance(t, int) else parse_duration_ns(t if isinstance(t, str) else f"{t}s")
        if ns % ctx.dt_ns:
            raise DynabrainError(f"event {label!r} at {format_duration(ns)} is not on a tick of "
                                 f"{format_duration(ctx.dt_ns)}")
        tick = ns // ctx.dt_ns
        with ctx.lock:
            ctx.scheduled.setdefault(tick, []).append((label, action))
        return tick
