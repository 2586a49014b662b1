"""``dynabrain plot LOG SIGNAL...``: a PNG of signals against simulated time, with the events marked.

A signal is named as on the bus (``core.aa.pos``), or without the core's name (``aa.pos``) when that
is unambiguous, and may pick one component (``aa.pos[2]``). Only the run is plotted: ticks that a
rollback discarded are left out (see `logs.read.final_mask`). One panel per signal, in its unit;
events are vertical lines (rollbacks dashed red), labelled on the top panel.
"""

from __future__ import annotations

import os
import re
from collections import Counter
from dataclasses import dataclass

import numpy as np

from ..kernel.suggest import did_you_mean
from .read import LogIndex, iter_bus, read_index
from .scan import LogError
from .schema import TOPIC_BUS

SKIPPED_EVENTS = ("layout", "expect", "run_end")
_COMPONENT = re.compile(r"^(.*)\[(\d+)\]$")


@dataclass(frozen=True)
class Wanted:
    text: str
    signal: str
    component: int | None
    unit: str


def plot(path: str | os.PathLike[str], signals: list[str], out: str | os.PathLike[str] | None = None) -> str:
    """Write the PNG and return its path (default: the log's path with ``.png``)."""
    path = os.fspath(path)
    if not signals:
        raise LogError("name at least one signal to plot")
    index = read_index(path)
    wanted = [resolve(index, s) for s in signals]
    times, values = _collect(path, index, wanted)
    out = os.fspath(out) if out is not None else (path[:-5] if path.endswith(".mcap") else path) + ".png"
    _draw(out, index, wanted, times, values)
    return out


def signal_names(index: LogIndex) -> dict[str, str]:
    """Every signal of every layout in the log -> its unit."""
    names: dict[str, str] = {}
    for cid in index.channels:
        if index.is_bus(cid):
            for slot in index.bus_codec(cid).slots:
                names.setdefault(slot.name, slot.unit)
    return names


def resolve(index: LogIndex, text: str) -> Wanted:
    """A signal as the user wrote it -> the bus signal (and component) it names."""
    names = signal_names(index)
    if not names:
        raise LogError(f"{index.path} has no dynabrain bus channel: there are no signals to plot")
    match = _COMPONENT.match(text)
    base, component = (match.group(1), int(match.group(2))) if match else (text, None)
    if base not in names:
        short = [n for n in names if n.endswith("." + base) and n.count(".") == base.count(".") + 1]
        if len(short) != 1:
            listed = ", ".join(sorted(names)[:15]) + (", ..." if len(names) > 15 else "")
            shorts = {n.split(".", 1)[1]: n for n in names if "." in n}
            hint = did_you_mean(base, [*names, *shorts])
            why = f"{base!r} is ambiguous ({', '.join(short)})" if short else f"no signal {base!r} in {index.path}"
            raise LogError(why + hint + f"; signals: {listed}")
        base = short[0]
    return Wanted(text, base, component, names[base])


def _collect(path: str, index: LogIndex, wanted: list[Wanted]) -> tuple[np.ndarray, list[np.ndarray]]:
    final = index.final(TOPIC_BUS)
    ticks: list[int] = []
    rows: list[list[np.ndarray | None]] = []
    for codec, _epoch, tick, row, pos, _topic in iter_bus(path, index):
        if pos not in final:
            continue
        ticks.append(tick)
        picked = []
        for w in wanted:
            slot = codec.by_name.get(w.signal)
            picked.append(None if slot is None else row[slot.offset:slot.offset + slot.size])
        rows.append(picked)
    order = np.argsort(ticks, kind="stable")
    dt = index.info.dt_ns if index.info else 1
    times = np.asarray(ticks, dtype=np.int64)[order] * dt / 1e9
    values = []
    for k, w in enumerate(wanted):
        width = max((len(r[k]) for r in rows if r[k] is not None), default=1)
        if w.component is not None and w.component >= width:
            raise LogError(f"{w.text}: {w.signal} has {width} component(s), so [{w.component}] does not exist")
        data = np.full((len(rows), width), np.nan)
        for i, r in enumerate(rows):
            if r[k] is not None:
                data[i, :len(r[k])] = r[k]
        data = data[order]
        values.append(data[:, [w.component]] if w.component is not None else data)
    return times, values


def _draw(out: str, index: LogIndex, wanted: list[Wanted], times: np.ndarray, values: list[np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(wanted), 1, sharex=True, figsize=(10, 2.6 * len(wanted) + 0.8), squeeze=False)
    for ax, w, data in zip(axes[:, 0], wanted, values, strict=True):
        labels = [w.text] if data.shape[1] == 1 else [f"{w.signal}[{i}]" for i in range(data.shape[1])]
        for i in range(data.shape[1]):
            ax.plot(times, data[:, i], label=labels[i], linewidth=1.1)
        ax.set_ylabel(w.unit if w.unit != "1" else "")
        ax.legend(loc="upper right", fontsize="small")
        ax.grid(alpha=0.3)
    _mark_events(axes[:, 0], index)
    axes[-1, 0].set_xlabel("simulated time (s)")
    name = index.info.scenario_name if index.info and index.info.scenario_name else os.path.basename(index.path)
    fig.suptitle(name)
    fig.tight_layout()
    try:
        fig.savefig(out, dpi=110)
    except OSError as exc:
        raise LogError(f"cannot write the plot {out}: {exc.strerror}") from None
    finally:
        plt.close(fig)


def _mark_events(axes, index: LogIndex) -> None:
    """A vertical line per event (rollbacks dashed red); one label per time on the top panel."""
    at: dict[float, list[str]] = {}
    for ev in index.events:
        if ev.get("kind") in SKIPPED_EVENTS:
            continue
        t = float(ev.get("time", 0.0))
        rollback = ev.get("kind") == "rollback"
        for ax in axes:
            ax.axvline(t, color="tab:red" if rollback else "0.4", linestyle="--" if rollback else ":", linewidth=0.9)
        at.setdefault(t, []).append(ev.get("kind", "?"))
    for t, kinds in list(at.items())[:40]:
        counts = Counter(kinds)
        label = ", ".join(k if n == 1 else f"{k} x{n}" for k, n in counts.items())
        axes[0].annotate(label, xy=(t, 1.0), xycoords=("data", "axes fraction"), rotation=90, fontsize="x-small",
                         va="top", ha="right", color="0.3")
