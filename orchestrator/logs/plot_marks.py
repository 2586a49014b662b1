"""What ``dynabrain plot`` draws besides the signals: events (lines, and bands for repeated edits) and the
run's expectation results.

Events. A kind of event that comes again and again a few ticks apart (a brain that sets an input every
tick: 1,200 ``set`` events) is one band, not a line per event: a run of at least `BAND_MIN` events of one
kind, each at most `BAND_GAP_TICKS` ticks after the one before, is drawn as a shaded span from its first to
its last, labelled with the kind, the count and what it edited (``set x1200: core.top.velocity``). The other
events are vertical lines (rollbacks dashed red), labelled on the top panel in groups of events closer than
1/60 of the time axis (``set x3, param``; at most `LABEL_GROUPS` groups, the rest counted).

Expectations. Each ``expect`` event (its label, whether it passed, the ticks it looked at) is a row of a strip
under the panels: a bar over the ticks it was checked on (a dot when that is one tick), green when it passed,
red when not, with its label; at most `EXPECT_ROWS` rows (the rest counted).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Any

SKIPPED_EVENTS = ("layout", "expect", "run_end")
LABEL_GROUPS = 40
"""Event labels drawn at most (groups of events close in time); the rest are counted."""
BAND_MIN = 8
"""Events of one kind in a run of at least this many become a band."""
BAND_GAP_TICKS = 5
"""Most ticks between two events of one band."""
EXPECT_ROWS = 12
"""Expectation results drawn at most; the rest are counted."""


@dataclass(frozen=True)
class Mark:
    """An event to draw: its time (s), kind and what it names (a ``set``'s signal, a ``param``'s name)."""

    time_s: float
    kind: str
    name: str = ""


@dataclass(frozen=True)
class Band:
    """A run of events of one kind (see the module docstring)."""

    start_s: float
    end_s: float
    kind: str
    count: int
    names: tuple[str, ...]

    @property
    def label(self) -> str:
        names = ", ".join(self.names[:2]) + (f" (+{len(self.names) - 2})" if len(self.names) > 2 else "")
        return f"{self.kind} x{self.count}" + (f": {names}" if names else "")


@dataclass(frozen=True)
class Result:
    """An expectation's result: its label, whether it passed, the times (s) it was checked over."""

    label: str
    passed: bool
    start_s: float
    end_s: float


def event_marks(events: list[dict], kinds: list[str] | None) -> list[Mark]:
    """The events to draw, in time order: ``kinds`` None for every kind but the bookkeeping ones
    (`SKIPPED_EVENTS`), else only those kinds."""
    out = []
    for ev in events:
        kind = str(ev.get("kind", "?"))
        if (kind in SKIPPED_EVENTS) if kinds is None else (kind not in kinds):
            continue
        detail = ev.get("detail") if isinstance(ev.get("detail"), dict) else {}
        out.append(Mark(float(ev.get("time", 0.0)), kind, str(detail.get("name", "") or "")))
    return sorted(out, key=lambda m: m.time_s)


def bands(marks: list[Mark], dt_s: float) -> tuple[list[Band], list[Mark]]:
    """Marks -> (bands of repeated events, the marks left single), see the module docstring."""
    by_kind: dict[str, list[Mark]] = {}
    for m in marks:
        by_kind.setdefault(m.kind, []).append(m)
    found, single = [], []
    gap = BAND_GAP_TICKS * dt_s * (1 + 1e-9)
    for kind, group in by_kind.items():
        run: list[Mark] = []
        for m in [*group, None]:
            if m is not None and run and m.time_s - run[-1].time_s <= gap:
                run.append(m)
                continue
            if len(run) >= BAND_MIN:
                names = tuple(n for n, _c in Counter(r.name for r in run if r.name).most_common())
                found.append(Band(run[0].time_s, run[-1].time_s, kind, len(run), names))
            else:
                single += run
            run = [m] if m is not None else []
    return sorted(found, key=lambda b: b.start_s), sorted(single, key=lambda m: m.time_s)


def results(events: list[dict], dt_s: float) -> list[Result]:
    """The run's expectation results (``expect`` events), in the order they were logged."""
    out = []
    for ev in events:
        if ev.get("kind") != "expect" or not isinstance(ev.get("detail"), dict):
            continue
        d = ev["detail"]
        end = d.get("to_tick")
        start = d.get("from_tick")
        end_s = float(end) * dt_s if isinstance(end, int) else float(ev.get("time", 0.0))
        start_s = float(start) * dt_s if isinstance(start, int) else end_s
        out.append(Result(str(d.get("name", "?")), bool(d.get("passed")), start_s, end_s))
    return out


def event_groups(events: list[tuple[float, str]], gap: float) -> list[tuple[float, str]]:
    """Events (time, kind), in time order -> one (time, label) per group of events less than ``gap``
    after the group's first: ``set x3, param`` (most frequent first, at most 40 characters)."""
    groups: list[list[tuple[float, str]]] = []
    for t, kind in events:
        if groups and t - groups[-1][0][0] <= gap:
            groups[-1].append((t, kind))
        else:
            groups.append([(t, kind)])
    out = []
    for group in groups:
        label = ", ".join(k if n == 1 else f"{k} x{n}" for k, n in Counter(k for _t, k in group).most_common())
        out.append((group[0][0], label if len(label) <= 40 else label[:39] + "…"))
    return out


# -- drawing (matplotlib axes) ------------------------------------------------------------------------
_BAND_COLORS = ("tab:purple", "tab:olive", "tab:cyan", "tab:brown", "tab:pink")


def draw_events(axes: list[Any], marks: list[Mark], dt_s: float) -> None:
    """Bands and lines on every panel, their labels on the top one."""
    found, single = bands(marks, dt_s)
    colors: dict[str, str] = {}
    top = axes[0]
    for k, band in enumerate(found):
        color = colors.setdefault(band.kind, _BAND_COLORS[len(colors) % len(_BAND_COLORS)])
        for ax in axes:
            ax.axvspan(band.start_s, max(band.end_s, band.start_s + dt_s), color=color, alpha=0.13, linewidth=0)
        top.annotate(band.label, xy=(band.start_s, 0.98 - 0.09 * (k % 4)), xycoords=("data", "axes fraction"),
                     fontsize="x-small", va="top", ha="left", color=color,
                     bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7})
    for m in single:
        rollback = m.kind == "rollback"
        for ax in axes:
            ax.axvline(m.time_s, color="tab:red" if rollback else "0.4", linestyle="--" if rollback else ":",
                       linewidth=0.9)
    if not single:
        return
    lo, hi = top.get_xlim()
    groups = event_groups([(m.time_s, m.kind) for m in single], (hi - lo) / 60 if hi > lo else 0.0)
    for t, label in groups[:LABEL_GROUPS]:
        top.annotate(label, xy=(t, 0.6), xycoords=("data", "axes fraction"), rotation=90, fontsize="x-small",
                     va="center", ha="right", color="0.25",
                     bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7})
    if len(groups) > LABEL_GROUPS:
        top.annotate(f"+{len(groups) - LABEL_GROUPS} more event groups", xy=(0.995, 0.02),
                     xycoords="axes fraction", ha="right", va="bottom", fontsize="x-small", color="0.3")


def draw_results(ax: Any, found: list[Result]) -> None:
    """The expectation strip (see the module docstring) on its own axes."""
    shown = found[:EXPECT_ROWS]
    lo, hi = ax.get_xlim()
    for row, r in enumerate(shown):
        y = len(shown) - row
        color = "tab:green" if r.passed else "tab:red"
        if r.end_s > r.start_s:
            ax.plot([r.start_s, r.end_s], [y, y], color=color, linewidth=4, solid_capstyle="butt")
        else:
            ax.plot([r.end_s], [y], marker="o", color=color, markersize=5)
        right = r.end_s < (lo + hi) / 2  # the label on the side with room
        ax.annotate(("pass: " if r.passed else "FAIL: ") + r.label, xy=(r.end_s, y), xytext=(5 if right else -5, 0),
                    textcoords="offset points", ha="left" if right else "right", va="center", fontsize="x-small",
                    color=color, bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.8})
    if len(found) > EXPECT_ROWS:
        ax.annotate(f"+{len(found) - EXPECT_ROWS} more expectations", xy=(0.995, 0.02), xycoords="axes fraction",
                    ha="right", va="bottom", fontsize="x-small", color="0.3")
    ax.set_ylim(0.3, len(shown) + 0.7)
    ax.set_yticks([])
    ax.set_ylabel("expect", fontsize="small")
    ax.grid(alpha=0.3, axis="x")
