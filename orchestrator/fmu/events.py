"""Event mode of one FMI 3.0 session with clocks (see `clocks` for what runs).

After each step (and at the end of initialization, where the FMU already is in event mode) the
session asks `Events.handle` for the time the step reached. When an input clock ticks there (a
time-based one by its interval, a triggered one whose port reads other than 0) or the FMU said it
needs event handling (an output clock it ticked during the step), the session:

1. enters event mode (``fmi3EnterEventMode``; not at initialization);
2. activates the ticking input clocks (``fmi3SetClock``) and sets their clocked inputs from the bus;
3. updates the discrete states (``fmi3UpdateDiscreteStates``) until they need no more update (an FMU
   that asks to end the simulation there ends it, as after a step);
4. reads the output clocks (``fmi3GetClock``; each port says 1 for the step at whose end it ticked),
   the clocked outputs of every clock that ticked, and the other outputs again;
5. goes back to step mode (``fmi3EnterStepMode``).

The schedule depends only on the time the FMU joined the world (``origin_ns``) and each clock's
interval and shift, fixed once the FMU is initialized: it holds no state of its own, so a rollback
that restores the FMU's state (always taken in step mode) replays the ticks bit for bit.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .clocks import FmuClock, whole_ns
from .errors import FMUCallError, FMUError, FMUTerminatedError

if TYPE_CHECKING:
    from .session import Group, Session

MAX_ITERATIONS = 100
"""Updates of the discrete states at one event before the FMU is said not to settle."""


class Events:
    """The clocks of one session and what ticks with each (built from the session's `info`)."""

    def __init__(self, session: Session):
        from .session import groups_at

        self.s = session
        info = session.info
        self.timed: list[FmuClock] = [c for c in info.clocks if c.timed]
        self.interval_ns: dict[int, int] = {}
        self.shift_ns: dict[int, int] = {}
        self.origin_ns = 0
        self.period_ns = 1
        """The module's period: every tick must fall at the end of one of its steps."""
        positions_in = _positions(info.inputs)
        positions_out = _positions(info.outputs)
        self.triggered = [(s.vrs[0], positions_in[s.name]) for s in info.inputs if s.type == "clock"]
        self.out_clocks = [(s.vrs[0], positions_out[s.name]) for s in info.outputs if s.type == "clock"]
        self.out_vrs = np.array([vr for vr, _ in self.out_clocks], dtype=np.uint32)
        self.clocked_in: dict[int, list[Group]] = {}
        self.clocked_out: dict[int, list[Group]] = {}
        for signals, positions, table in ((info.inputs, positions_in, self.clocked_in),
                                          (info.outputs, positions_out, self.clocked_out)):
            for clock in info.clocks:
                mine = [(s, positions[s.name]) for s in signals if s.type != "clock" and clock.vr in s.clocks]
                if mine:
                    table[clock.vr] = groups_at(session.api, mine)

    # -- the schedule ------------------------------------------------------------------------------
    def start(self, origin_ns: int) -> None:
        """At the end of initialization (the FMU is in event mode): fix each time-based clock's
        interval, then handle the event at ``origin_ns`` (the world time the FMU joined at)."""
        self.origin_ns = origin_ns
        for clock in self.timed:
            interval = clock.interval
            if interval is None:  # calculated: the FMU knows it now
                values, qualifiers = self.s.api.get_intervals(np.array([clock.vr], dtype=np.uint32))
                if qualifiers[0] == 0 or not values[0] > 0:
                    raise FMUError(f"{self.s.info.label}: clock {clock.name!r} ({clock.variability}) has no period "
                                   "after initialization")
                interval = float(values[0])
            what = f"module {self.s.name!r}: the {{}} of clock {clock.name!r}"
            self.interval_ns[clock.vr] = whole_ns(interval, what.format("interval"), self.period_ns)
            self.shift_ns[clock.vr] = whole_ns(clock.shift, what.format("shift"), self.period_ns)
        self.handle(origin_ns, False, in_event_mode=True)

    def due(self, t_ns: int) -> list[int]:
        """The time-based clocks that tick at world time ``t_ns``."""
        out = []
        for clock in self.timed:
            since = t_ns - self.origin_ns - self.shift_ns[clock.vr]
            if since >= 0 and since % self.interval_ns[clock.vr] == 0:
                out.append(clock.vr)
        return out

    # -- an event ----------------------------------------------------------------------------------
    def before_step(self) -> None:
        """Output clock ports say 1 only for the step at whose end their clock ticked."""
        out = self.s.out_values
        for _, at in self.out_clocks:
            out[at] = 0.0

    def handle(self, t_ns: int, needed: bool, *, in_event_mode: bool = False) -> bool:
        """Handle what happens at world time ``t_ns`` (see the module docstring); whether an event
        was handled. ``needed``: the FMU said so (``eventHandlingNeeded``)."""
        s, api = self.s, self.s.api
        active = self.due(t_ns) + [vr for vr, at in self.triggered if s.in_values[at] != 0]
        if not active and not needed:
            if in_event_mode:
                api.enter_step_mode()
            return False
        if not in_event_mode:
            api.enter_event_mode()
        if active:
            api.set_clocks(np.array(active, dtype=np.uint32), np.ones(len(active), dtype=np.bool_))
            for vr in active:
                for g in self.clocked_in.get(vr, ()):
                    s.write_group(g)
        for _ in range(MAX_ITERATIONS):
            more, terminate = api.update_discrete_states()
            if terminate:
                said = api.sink.take()
                raise FMUTerminatedError(s.name, "fmi3UpdateDiscreteStates", None,
                                         f"{s.info.label} asked to end the simulation in event mode at "
                                         f"t={t_ns / 1e9 + s.start_time:g} s" + (" (" + " | ".join(said) + ")"
                                                                                  if said else ""))
            if not more:
                break
        else:
            raise FMUCallError(s.name, "fmi3UpdateDiscreteStates", None,
                               f"{s.info.label}: the discrete states still need an update after {MAX_ITERATIONS} "
                               f"updates at t={t_ns / 1e9 + s.start_time:g} s")
        ticked = list(active)
        if len(self.out_vrs):
            for (vr, at), on in zip(self.out_clocks, api.get_clocks(self.out_vrs), strict=True):
                s.out_values[at] = 1.0 if on else 0.0
                if on:
                    ticked.append(vr)
        for vr in ticked:
            for g in self.clocked_out.get(vr, ()):
                s.read_group(g)
        s.read_outputs()
        api.enter_step_mode()
        return True


def _positions(signals: tuple) -> dict[str, int]:
    """Each signal's first position in the flat array of its direction."""
    out, at = {}, 0
    for sig in signals:
        out[sig.name] = at
        at += sig.size
    return out
