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

The schedule of the fixed clocks depends only on the time the FMU joined the world (``origin_ns``)
and each clock's interval and shift, fixed once the FMU is initialized. The clocks whose interval the
FMU gives (tunable, changing, countdown: `clocks.DYNAMIC`) have a schedule that is state: their
next tick and interval (`Schedule`), read with ``fmi3GetIntervalDecimal`` at initialization and after
the discrete states are updated at every event (a qualifier ``fmi3IntervalChanged`` counts the new
interval from that event; a changing clock's interval is read at each of its ticks; a countdown
clock that ticked has no next tick until the FMU starts another countdown). The session's state pool
saves that schedule with each FMU state (taken in step mode, after the events), so a rollback, a
fork and an isolated restart replay the ticks bit for bit.
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
        self.schedule = Schedule([c for c in info.clocks if c.dynamic]) if any(c.dynamic for c in info.clocks) \
            else None
        """The clocks whose interval the FMU gives, and when each ticks next (state), or None."""
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
        if self.schedule is not None:
            self.schedule.start(self, origin_ns)
        if self.s.info.scheduled:
            self.activate(origin_ns)
        else:
            self.handle(origin_ns, False, in_event_mode=True)

    def due(self, t_ns: int) -> list[int]:
        """The time-based clocks that tick at world time ``t_ns``."""
        out = []
        for clock in self.timed:
            since = t_ns - self.origin_ns - self.shift_ns[clock.vr]
            if since >= 0 and since % self.interval_ns[clock.vr] == 0:
                out.append(clock.vr)
        if self.schedule is not None:
            out += self.schedule.due(t_ns)
        return out

    def whole(self, seconds: float, clock: FmuClock, t_ns: int, *, zero: bool = False) -> int:
        """An interval the FMU gave, in nanoseconds: a whole number of the module's periods (above 0,
        or 0 where ``zero``), else an error naming the clock and the time."""
        ns = round(seconds * 1e9) if np.isfinite(seconds) else -1
        if ns < 0 or (ns == 0 and not zero) or abs(ns - seconds * 1e9) > 1e-3 or ns % self.period_ns:
            raise FMUCallError(self.s.name, "fmi3GetIntervalDecimal", None,
                               f"{self.s.info.label}: clock {clock.name!r} ({clock.variability}) was given the "
                               f"interval {seconds:g} s at t={t_ns / 1e9 + self.s.start_time:g} s, not a "
                               f"{'' if zero else 'positive '}whole number of the module's periods "
                               f"({self.period_ns / 1e9:g} s): its tick would fall between two steps")
        return ns

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
        if self.schedule is not None:
            self.schedule.after_event(self, t_ns, active)
        ticked = list(active)
        if len(self.out_vrs):
            for (vr, at), on in zip(self.out_clocks, api.get_clocks(self.out_vrs), strict=True):
                if on:  # (0 from the step's start: `before_step`; an early return's event may have ticked it)
                    s.out_values[at] = 1.0
                    ticked.append(vr)
        for vr in ticked:
            for g in self.clocked_out.get(vr, ()):
                s.read_group(g)
        s.read_outputs()
        api.enter_step_mode()
        return True


    def activate(self, t_ns: int) -> bool:
        """Scheduled execution (no event mode, no steps): at world time ``t_ns``, run the model
        partition of each input clock that ticks there (`due`, or a triggered one whose port reads other
        than 0), in priority order: its clocked inputs set from the bus, ``fmi3ActivateModelPartition``,
        its clocked outputs read. Then the next ticks of the clocks whose interval the FMU gives, the
        output clocks (``fmi3GetClock``: each port says 1 at the tick it ticked) with their clocked
        outputs, and the other outputs. A countdown a partition gives the interval 0 ticks at once, its
        partition run after the others (the Reference FMU Clocks does that). Whether a partition ran."""
        s, api = self.s, self.s.api
        self.before_step()
        active = self.due(t_ns) + [vr for vr, at in self.triggered if s.in_values[at] != 0]
        if not active:
            return False
        priority = {c.vr: c.priority for c in s.info.clocks}
        t = t_ns / 1e9 + s.start_time
        done: set[int] = set()
        for _ in range(MAX_ITERATIONS):  # a partition may start a countdown of 0: that clock ticks now too
            active.sort(key=lambda vr: (priority.get(vr, 0), vr))
            for vr in active:
                for g in self.clocked_in.get(vr, ()):
                    s.write_group(g)
                api.activate(vr, t)
                for g in self.clocked_out.get(vr, ()):
                    s.read_group(g)
            done.update(active)
            if self.schedule is None:
                break
            self.schedule.after_event(self, t_ns, active)
            active = [vr for vr in self.schedule.due(t_ns) if vr not in done]
            if not active:
                break
        else:
            raise FMUCallError(s.name, "fmi3ActivateModelPartition", None,
                               f"{s.info.label}: clocks still due at t={t:g} s after {MAX_ITERATIONS} rounds of "
                               "partitions (countdowns of 0 started again and again)")
        if len(self.out_vrs):
            for (vr, at), on in zip(self.out_clocks, api.get_clocks(self.out_vrs), strict=True):
                if on:
                    s.out_values[at] = 1.0
                    for g in self.clocked_out.get(vr, ()):
                        s.read_group(g)
        s.read_outputs()
        return True


class Schedule:
    """When each clock whose interval the FMU gives ticks next (world ns; -1: not scheduled) and its
    last interval (tunable, changing): the state `save` and `load` carry with the FMU's state."""

    def __init__(self, clocks: list[FmuClock]):
        self.clocks = clocks
        self.vrs = np.array([c.vr for c in clocks], dtype=np.uint32)
        self.next_ns = np.full(len(clocks), -1, dtype=np.int64)
        self.interval_ns = np.zeros(len(clocks), dtype=np.int64)

    def save(self) -> bytes:
        return self.next_ns.tobytes() + self.interval_ns.tobytes()

    def load(self, data: bytes) -> None:
        both = np.frombuffer(data, dtype=np.int64)
        n = len(self.clocks)
        self.next_ns[:], self.interval_ns[:] = both[:n], both[n:]

    def due(self, t_ns: int) -> list[int]:
        return [int(vr) for vr in self.vrs[self.next_ns == t_ns]]

    def start(self, events: Events, origin_ns: int) -> None:
        """After initialization: the first tick of each clock (a tunable one at its shift, the others
        the interval after the start; a countdown not yet known: none)."""
        s = events.s
        intervals, qualifiers = s.api.get_intervals(self.vrs)
        for i, (c, seconds, q) in enumerate(zip(self.clocks, intervals, qualifiers, strict=True)):
            if q == 0 and c.variability != "countdown":
                raise FMUError(f"{s.info.label}: clock {c.name!r} ({c.variability}) has no interval after "
                               "initialization (fmi3GetIntervalDecimal: fmi3IntervalNotYetKnown)")
            if q == 0:
                continue
            if c.variability == "tunable":
                self.interval_ns[i] = events.whole(float(seconds), c, origin_ns)
                shift = whole_ns(c.shift, f"module {s.name!r}: the shift of clock {c.name!r}", events.period_ns)
                self.next_ns[i] = origin_ns + shift
            else:
                self.interval_ns[i] = events.whole(float(seconds), c, origin_ns, zero=True)
                self.next_ns[i] = origin_ns + self.interval_ns[i]

    def after_event(self, events: Events, t_ns: int, active: list[int]) -> None:
        """After the discrete states are updated at ``t_ns`` (``active``: the input clocks that
        ticked): read the intervals and schedule the next ticks."""
        intervals, qualifiers = events.s.api.get_intervals(self.vrs)
        for i, (c, seconds, q) in enumerate(zip(self.clocks, intervals, qualifiers, strict=True)):
            ticked = c.vr in active
            if q == 2 and (t_ns - events.origin_ns) % events.period_ns:
                raise FMUCallError(events.s.name, "fmi3GetIntervalDecimal", None,
                                   f"{events.s.info.label}: clock {c.name!r} ({c.variability}) was given an interval "
                                   f"at an event between two steps (t={t_ns / 1e9 + events.s.start_time:g} s, an "
                                   "early return): its ticks would fall between two steps")
            if q == 2:  # fmi3IntervalChanged: counted from this event (a countdown of 0: it ticks now)
                self.interval_ns[i] = events.whole(float(seconds), c, t_ns, zero=c.variability == "countdown")
                self.next_ns[i] = t_ns + self.interval_ns[i]
            elif ticked and c.variability == "countdown":
                self.next_ns[i] = -1  # ran out; the FMU starts another countdown when it will
            elif ticked and c.variability == "changing" and q == 0:
                raise FMUCallError(events.s.name, "fmi3GetIntervalDecimal", None,
                                   f"{events.s.info.label}: changing clock {c.name!r} ticked at "
                                   f"t={t_ns / 1e9 + events.s.start_time:g} s and gave no next interval")
            elif ticked:  # periodic (tunable), or a changing clock that kept its interval
                self.next_ns[i] = t_ns + self.interval_ns[i]
            elif q == 0 and c.variability == "countdown":
                self.next_ns[i] = -1


def _positions(signals: tuple) -> dict[str, int]:
    """Each signal's first position in the flat array of its direction."""
    out, at = {}, 0
    for sig in signals:
        out[sig.name] = at
        at += sig.size
    return out
