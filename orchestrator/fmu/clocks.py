"""FMI 3.0 clocks in co-simulation, as the adapter runs them.

An FMU with clocks runs with event mode (``eventModeUsed``). Its clocks:

- a time-based input clock (``intervalVariability`` constant, fixed or calculated: an interval
  that does not change once the FMU is initialized) ticks every ``interval`` from the FMU's start
  plus ``shift``; the module ticks it itself, in event mode at the end of the step that reaches the
  tick. Its interval and shift must be whole multiples of the module's period (refused at setup
  otherwise), and one without an interval is refused at load;
- a triggered input clock is an input port (unit ``clock``): a step that reads a value other than 0
  ticks it at its end;
- an output clock is an output port (unit ``clock``): 1 after a step at whose end it ticked, else 0.

- an input clock whose interval the FMU gives while it runs (``intervalVariability`` tunable without
  ``intervalDecimal``, changing, countdown): the module ticks it too, at the times the FMU says
  (``fmi3GetIntervalDecimal`` with its qualifiers, read in initialization and after every event;
  see `events`): a tunable clock is periodic and a changed interval counts from the event it was
  read at; a changing clock's next interval is read at each of its ticks; a countdown clock ticks
  once when the interval read (``fmi3IntervalChanged``) runs out. Each interval must be a positive
  whole number of the module's periods (a run-time error naming the clock and the time otherwise).
  A tunable clock with ``intervalDecimal`` is run as a constant one (the master never sets it).

Clock ports connect only to clock ports (the bus refuses a connection between units ``clock`` and
anything else). Clocked variables (``clocks="..."``) are set and read only in event mode, at the
ticks of their clocks; in between the bus holds their last values.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import FMUError

TIME_BASED = ("constant", "fixed", "calculated")
"""Input clocks whose interval is known once the FMU is initialized: the module ticks them."""
DYNAMIC = ("tunable", "changing", "countdown")
"""Input clocks whose interval the FMU gives while it runs: the module ticks them when it says."""
CLOCK_UNIT = "clock"


@dataclass(frozen=True)
class FmuClock:
    """A Clock variable of the model description."""

    name: str
    vr: int
    causality: str
    """``input`` or ``output``."""
    variability: str
    """``intervalVariability``: ``constant``, ``fixed``, ``calculated``, ``triggered``, ..."""
    interval: float | None
    """Seconds (``intervalDecimal``), when the description gives it."""
    shift: float
    description: str
    priority: int = 0
    """Scheduled execution: the order partitions that tick together run in (0 first)."""

    @property
    def timed(self) -> bool:
        """An input clock the module ticks itself, by a fixed interval."""
        return self.causality == "input" and (self.variability in TIME_BASED
                                              or (self.variability == "tunable" and self.interval is not None))

    @property
    def dynamic(self) -> bool:
        """An input clock the module ticks itself, when the FMU says (see `DYNAMIC`)."""
        return self.causality == "input" and self.variability in DYNAMIC and not self.timed

    @property
    def on_bus(self) -> bool:
        """A triggered input clock or an output clock: a port of unit ``clock``."""
        return not self.timed and not self.dynamic


def read_clocks(path: Path, md: Any, name: str) -> tuple[FmuClock, ...]:
    """The FMU's clocks (FMPy reads the Clock elements without their intervals: read them here)."""
    clocks = [v for v in md.modelVariables if v.type == "Clock"]
    if not clocks:
        return ()
    with zipfile.ZipFile(path) as zf:
        root = ET.fromstring(zf.read("modelDescription.xml"))
    attrs = {int(e.get("valueReference", -1)): e.attrib for e in root.iter("Clock")}
    out = []
    for v in clocks:
        a = attrs.get(v.valueReference, {})
        variability = a.get("intervalVariability", "")
        clock = FmuClock(v.name, v.valueReference, v.causality, variability,
                         float(a["intervalDecimal"]) if "intervalDecimal" in a else None,
                         float(a.get("shiftDecimal", 0.0)), v.description or "", int(a.get("priority", 0)))
        if v.causality not in ("input", "output"):
            raise FMUError(f"FMU {name}: clock {v.name!r} is a {v.causality} clock; the adapter runs input and output "
                           "clocks")
        if v.causality == "input" and variability not in (*TIME_BASED, *DYNAMIC, "triggered"):
            raise FMUError(f"FMU {name}: clock {v.name!r} is {variability or 'of no interval variability'}; the "
                           "adapter runs constant, fixed, calculated, tunable, changing, countdown and triggered "
                           "input clocks")
        if clock.timed and variability == "constant" and not (clock.interval and clock.interval > 0):
            raise FMUError(f"FMU {name}: clock {v.name!r} ({variability}) has no period: it declares no "
                           "intervalDecimal")
        out.append(clock)
    if md.coSimulation is not None and not md.coSimulation.hasEventMode:  # (scheduled execution: none needed)
        raise FMUError(f"FMU {name}: it has clocks ({', '.join(c.name for c in out)}) but no event mode "
                       "(hasEventMode is false): a co-simulation FMU ticks its clocks in event mode")
    return tuple(out)


def whole_ns(seconds: float, what: str, period_ns: int) -> int:
    """``seconds`` as nanoseconds, a whole multiple of ``period_ns`` (else `FMUError` saying ``what``)."""
    ns = round(seconds * 1e9)
    if abs(ns - seconds * 1e9) > 1e-3 or (ns <= 0 and what.endswith("interval")) or ns % period_ns:
        raise FMUError(f"{what} is {seconds:g} s, not a whole number of the module's periods "
                       f"({period_ns / 1e9:g} s): its ticks would fall between two steps")
    return ns


def check_periods(clocks: tuple[FmuClock, ...], period_ns: int, module: str) -> None:
    """Refuse a time-based clock whose ticks fall between the module's steps."""
    for c in clocks:
        if c.timed and c.interval is not None:
            whole_ns(c.interval, f"module {module!r}: the interval of clock {c.name!r}", period_ns)
            whole_ns(c.shift, f"module {module!r}: the shift of clock {c.name!r}", period_ns)
