"""``dynabrain plot LOG SIGNAL...``: a PNG of signals against simulated time, with the events marked.

A signal is named as on the bus (``core.aa.pos``), or without the core's name (``aa.pos``) when that
is unambiguous, and may pick one component: by its flat index (``aa.pos[2]``, ``zmp.cop[4]``), by its
index in each dimension (``zmp.cop[1, 1]``) or by its labels (``aa.pos[z]``, ``zmp.cop[r_foot, y]``).

Labels. A component is labelled by row and column, not by its flat index: a row of a block port by
the name of the port that views it (``zmp.cop`` (2, 3) has the views ``zmp.l_foot.cop`` and
``zmp.r_foot.cop``: rows ``l_foot`` and ``r_foot``), the last dimension by axis when it is a 3-vector
of a spatial unit (m, m/s, m/s^2, rad/s, rad/s^2, N, N*m: ``x y z``) or a quaternion (a ``quat``:
``w x y z``), anything else by its index: ``zmp.cop[l_foot, x]``, ``noise.y[1]``, ``m.k[0, 2]``.

Only the run is plotted: ticks that a rollback discarded are left out (see `logs.read.final_mask`).
One panel per signal, in its unit. Events are vertical lines (rollbacks dashed red); their labels go
on the top panel, one per group of events closer together than 1/60 of the time axis (``set x3,
param``), at most 40 groups labelled (the rest are counted in the corner).
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
from .schema import TOPIC_BUS, Slot

SKIPPED_EVENTS = ("layout", "expect", "run_end")
_COMPONENT = re.compile(r"^(.*)\[([^\[\]]+)\]$")
SPATIAL_UNITS = ("m", "m/s", "m/s^2", "m/s2", "rad/s", "rad/s^2", "rad/s2", "N", "N*m", "Nm")
LABEL_GROUPS = 40
"""Event labels drawn at most (groups of events close in time); the rest are counted."""


@dataclass(frozen=True)
class Wanted:
    text: str
    signal: str
    component: int | None
    unit: str
    labels: tuple[str, ...] = ()
    """Each component's label (``[l_foot, x]``), in flat order."""


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
    base, picked = (match.group(1).strip(), match.group(2)) if match else (text, None)
    if base not in names:
        short = [n for n in names if n.endswith("." + base) and n.count(".") == base.count(".") + 1]
        if len(short) != 1:
            listed = ", ".join(sorted(names)[:15]) + (", ..." if len(names) > 15 else "")
            shorts = {n.split(".", 1)[1]: n for n in names if "." in n}
            hint = did_you_mean(base, [*names, *shorts])
            why = f"{base!r} is ambiguous ({', '.join(short)})" if short else f"no signal {base!r} in {index.path}"
            raise LogError(why + hint + f"; signals: {listed}")
        base = short[0]
    slot, slots = _slot(index, base)
    labels = tuple(component_labels(slot, slots)) if slot is not None else ()
    return Wanted(text, base, None if picked is None else _component(text, base, picked, slot, slots), names[base],
                  labels)


def _slot(index: LogIndex, name: str) -> tuple[Slot | None, dict[str, Slot]]:
    """The slot of signal ``name`` in the first layout that has it, and that layout's slots."""
    for cid in index.channels:
        if index.is_bus(cid):
            by_name = index.bus_codec(cid).by_name
            if name in by_name:
                return by_name[name], by_name
    return None, {}


def _component(text: str, signal: str, picked: str, slot: Slot | None, slots: dict[str, Slot]) -> int:
    """A component as written between brackets (flat index, an index per dimension, or labels) -> its
    flat index (checked against the signal's size when the data is read)."""
    parts = [p.strip() for p in picked.split(",")]
    if len(parts) == 1 and parts[0].isdigit():
        return int(parts[0])
    shape = slot.shape if slot is not None else ()
    if len(parts) != len(shape):
        raise LogError(f"{text}: {signal} has shape {list(shape)}; name one index per dimension "
                       f"({', '.join(['i'] * max(len(shape), 1))}) or one flat index")
    names = axis_labels(slot, slots)
    flat = 0
    for dim, (part, size, labels) in enumerate(zip(parts, shape, names, strict=True)):
        if part.isdigit() and int(part) < size:
            at = int(part)
        elif part in labels:
            at = labels.index(part)
        else:
            raise LogError(f"{text}: [{part}] is no index of dimension {dim} of {signal} (0..{size - 1}"
                           + (f" or {', '.join(labels)})" if any(not x.isdigit() for x in labels) else ")"))
        flat = flat * size + at
    return flat


def axis_labels(slot: Slot, slots: dict[str, Slot]) -> list[list[str]]:
    """Per dimension of ``slot``'s shape, a label for each index (see the module docstring)."""
    shape = slot.shape
    out = [[str(i) for i in range(n)] for n in shape]
    if not shape or len(shape) > 2:
        return out
    if shape[-1] == 3 and slot.unit in SPATIAL_UNITS:
        out[-1] = ["x", "y", "z"]
    elif shape[-1] == 4 and slot.name.rsplit(".", 1)[-1] in ("quat", "quaternion"):
        out[-1] = ["w", "x", "y", "z"]
    if len(shape) == 1 and out[0][0] != "0":
        return out  # a vector with axes: no rows to name
    rows, inner = shape[0], shape[1:]
    size = int(np.prod(inner, dtype=np.int64))
    module, own = slot.name.split(".", 1)[0], slot.name.rsplit(".", 1)[-1]
    at = {(s.offset, s.shape): s.name for s in slots.values() if s is not slot and s.name.startswith(module + ".")}
    for i in range(rows):
        view = at.get((slot.offset + i * size, inner))
        if view is not None:
            label = view[len(module) + 1:]
            out[0][i] = label[:-len(own) - 1] if label.endswith("." + own) and label != own else label
    return out


def component_labels(slot: Slot, slots: dict[str, Slot]) -> list[str]:
    """Each component's label, in flat (row-major) order: ``[l_foot, x]``, ``[x]``, ``[0, 2]``."""
    if not slot.shape:
        return [""]
    names = axis_labels(slot, slots)
    grid = np.indices(slot.shape).reshape(len(slot.shape), -1).T
    return ["[" + ", ".join(names[d][i] for d, i in enumerate(idx)) + "]" for idx in grid]


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
        if data.shape[1] == 1:
            labels = [w.text if w.component is None or len(w.labels) <= w.component
                      else w.signal + w.labels[w.component]]
        else:
            names = w.labels if len(w.labels) == data.shape[1] else [f"[{i}]" for i in range(data.shape[1])]
            labels = [w.signal + n for n in names]
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
    """A vertical line per event (rollbacks dashed red); on the top panel, one label per group of events
    closer together than 1/60 of the time axis, for at most `LABEL_GROUPS` groups."""
    events = sorted(((float(ev.get("time", 0.0)), str(ev.get("kind", "?"))) for ev in index.events
                     if ev.get("kind") not in SKIPPED_EVENTS), key=lambda e: e[0])
    for t, kind in events:
        rollback = kind == "rollback"
        for ax in axes:
            ax.axvline(t, color="tab:red" if rollback else "0.4", linestyle="--" if rollback else ":", linewidth=0.9)
    if not events:
        return
    lo, hi = axes[0].get_xlim()
    groups = event_groups(events, (hi - lo) / 60 if hi > lo else 0.0)
    for t, label in groups[:LABEL_GROUPS]:
        axes[0].annotate(label, xy=(t, 0.98), xycoords=("data", "axes fraction"), rotation=90,
                         fontsize="x-small", va="top", ha="right", color="0.25",
                         bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7})
    if len(groups) > LABEL_GROUPS:
        axes[0].annotate(f"+{len(groups) - LABEL_GROUPS} more event groups", xy=(0.995, 0.02),
                         xycoords="axes fraction", ha="right", va="bottom", fontsize="x-small", color="0.3")


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
