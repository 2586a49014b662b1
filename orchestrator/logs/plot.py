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
One panel per signal, in its unit; one panel per component with ``split``, or when the components'
scales differ (of the components that move, the largest range over `SCALE_RATIO` times the smallest:
a block's small x/y motion is not flattened against its z). Lines that share a panel differ in colour,
dash and sparse markers, so that one hidden under another still shows. Events (``events``: which
kinds; all but the bookkeeping ones by default) are lines, and a kind repeated every few ticks a band
(`logs.plot_marks`); ``expectations`` adds a strip with the run's expectation results; ``imagined``
overlays the log's imagined futures (``/imagined/<name>/<branch>/bus``) of the same signals, dashed,
in their line's colour.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

import numpy as np

from ..kernel.suggest import did_you_mean
from .plot_marks import draw_events, draw_results, event_groups, event_marks, results
from .read import LogIndex, iter_bus, read_index
from .scan import LogError, Message, scan
from .schema import IMAGINED, TOPIC_BUS, BusCodec, Slot

__all__ = ["PlotOptions", "event_groups", "plot", "resolve", "signal_names"]
_COMPONENT = re.compile(r"^(.*)\[([^\[\]]+)\]$")
SPATIAL_UNITS = ("m", "m/s", "m/s^2", "m/s2", "rad/s", "rad/s^2", "rad/s2", "N", "N*m", "Nm")
SCALE_RATIO = 10.0
"""Components whose ranges differ by more than this factor get a panel each."""
MAX_FUTURES = 30
"""Imagined futures overlaid at most (the first ones in the log; the rest are counted)."""
_STYLES = ("-", "--", "-.", ":")
_MARKERS = ("o", "s", "^", "v", "D", "x", "P", "*")


@dataclass(frozen=True)
class Wanted:
    text: str
    signal: str
    component: int | None
    unit: str
    labels: tuple[str, ...] = ()
    """Each component's label (``[l_foot, x]``), in flat order."""


@dataclass(frozen=True)
class PlotOptions:
    """What is drawn besides the signals (see the module docstring). ``events``: None for every kind but the
    bookkeeping ones, else the kinds to mark (empty: none)."""

    events: tuple[str, ...] | None = None
    imagined: bool = False
    expectations: bool = True
    split: bool = False


@dataclass(frozen=True)
class Future:
    """An imagined future of the plotted signals: its label, times (s), and per wanted signal its values
    (or None when the future did not record it)."""

    label: str
    times: np.ndarray
    values: list[np.ndarray | None]


def plot(path: str | os.PathLike[str], signals: list[str], out: str | os.PathLike[str] | None = None,
         options: PlotOptions | None = None) -> str:
    """Write the PNG and return its path (default: the log's path with ``.png``)."""
    path = os.fspath(path)
    options = options or PlotOptions()
    if not signals:
        raise LogError("name at least one signal to plot")
    index = read_index(path)
    wanted = [resolve(index, s) for s in signals]
    times, values = _collect(path, index, wanted)
    futures = _futures(index, wanted) if options.imagined else []
    out = os.fspath(out) if out is not None else (path[:-5] if path.endswith(".mcap") else path) + ".png"
    _draw(out, index, wanted, times, values, futures, options)
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


def _futures(index: LogIndex, wanted: list[Wanted]) -> list[Future]:
    """The imagined futures (``/imagined/<name>/<branch>/bus``) that recorded any of the wanted signals."""
    codecs: dict[int, tuple[str, BusCodec]] = {}
    for cid, ch in index.channels.items():
        if ch.topic.startswith(IMAGINED + "/") and ch.topic.endswith(TOPIC_BUS) and "layout" in ch.metadata:
            codec = BusCodec.from_metadata(ch.metadata)
            if any(w.signal in codec.by_name for w in wanted):
                codecs[cid] = (ch.topic[len(IMAGINED) + 1:-len(TOPIC_BUS)], codec)
    rows: dict[int, list[tuple[int, np.ndarray]]] = {cid: [] for cid in codecs}
    if codecs:
        for rec in scan(index.path):
            if isinstance(rec, Message) and rec.channel_id in codecs:
                decoded, ticks, _epochs = codecs[rec.channel_id][1].decode(np.frombuffer(rec.data, dtype=np.uint8))
                rows[rec.channel_id].append((int(ticks[0]), decoded[0]))
    dt = index.info.dt_ns if index.info else 1
    out = []
    for cid, (label, codec) in codecs.items():
        got = sorted(rows[cid], key=lambda r: r[0])
        picked: list[np.ndarray | None] = []
        for w in wanted:
            slot = codec.by_name.get(w.signal)
            if slot is None or (w.component is not None and w.component >= slot.size):
                picked.append(None)
                continue
            data = np.array([r[slot.offset:slot.offset + slot.size] for _t, r in got]).reshape(len(got), slot.size)
            picked.append(data[:, [w.component]] if w.component is not None else data)
        out.append(Future(label, np.array([t for t, _r in got], dtype=np.int64) * dt / 1e9, picked))
    return out


@dataclass(frozen=True)
class Panel:
    """A panel: wanted signal ``k``'s columns ``columns``."""

    k: int
    columns: tuple[int, ...]


def panels(values: list[np.ndarray], split: bool) -> list[Panel]:
    """One panel per signal, or per component when ``split`` or when the scales differ (`SCALE_RATIO`)."""
    out = []
    for k, data in enumerate(values):
        width = data.shape[1]
        if width > 1 and (split or _scales_differ(data)):
            out += [Panel(k, (i,)) for i in range(width)]
        else:
            out.append(Panel(k, tuple(range(width))))
    return out


def _scales_differ(data: np.ndarray) -> bool:
    finite = np.where(np.isfinite(data), data, np.nan)
    if not np.isfinite(finite).any(axis=0).all():
        return False
    ranges = np.nanmax(finite, axis=0) - np.nanmin(finite, axis=0)
    moving = ranges[ranges > 0]  # a constant component is a flat line on any scale
    return bool(len(moving) > 1 and moving.max() > SCALE_RATIO * moving.min())


def _draw(out: str, index: LogIndex, wanted: list[Wanted], times: np.ndarray, values: list[np.ndarray],
          futures: list[Future], options: PlotOptions) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    laid = panels(values, options.split)
    dt_s = (index.info.dt_ns if index.info else 1) / 1e9
    found = results(index.events, dt_s) if options.expectations else []
    strip = min(len(found), 12) * 0.22 + 0.4 if found else 0.0
    heights = [2.4] * len(laid) + ([strip] if found else [])
    fig, axes = plt.subplots(len(heights), 1, sharex=True, figsize=(10, sum(heights) + 0.9), squeeze=False,
                             gridspec_kw={"height_ratios": heights})
    plotted = axes[:len(laid), 0]
    for ax, panel in zip(plotted, laid, strict=True):
        _draw_panel(ax, wanted[panel.k], panel, times, values[panel.k], futures[:MAX_FUTURES])
    marks = event_marks(index.events, None if options.events is None else list(options.events))
    draw_events(list(plotted), marks, dt_s)
    if found:
        draw_results(axes[-1, 0], found)
    if len(futures) > MAX_FUTURES:
        plotted[0].annotate(f"{len(futures) - MAX_FUTURES} more imagined futures not drawn", xy=(0.005, 0.02),
                            xycoords="axes fraction", fontsize="x-small", color="0.3")
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


def _draw_panel(ax, w: Wanted, panel: Panel, times: np.ndarray, data: np.ndarray, futures: list[Future]) -> None:
    """The run's lines of one panel (each its colour, dash and sparse markers) and the futures' dashed."""
    width = data.shape[1]
    if width == 1:
        labels = [w.text if w.component is None or len(w.labels) <= w.component else w.signal + w.labels[w.component]]
    else:
        names = w.labels if len(w.labels) == width else [f"[{i}]" for i in range(width)]
        labels = [w.signal + n for n in names]
    every = max(1, len(times) // 12)
    for n, i in enumerate(panel.columns):
        color = f"C{i % 10}"
        ax.plot(times, data[:, i], label=labels[i], color=color, linewidth=1.2, linestyle=_STYLES[n % len(_STYLES)],
                marker=_MARKERS[n % len(_MARKERS)], markevery=(n * every // max(len(panel.columns), 1), every),
                markersize=4, markerfacecolor="none")
        for f, future in enumerate(futures):
            got = future.values[panel.k]
            if got is not None and len(future.times):
                ax.plot(future.times, got[:, i], color=color, linewidth=1.0, alpha=0.8, linestyle=(0, (2, 2)),
                        zorder=3, label="imagined" if n == 0 and f == 0 else None)  # on top: thin and dashed
    ax.set_ylabel(w.unit if w.unit != "1" else "")
    ax.legend(loc="upper right", fontsize="small")
    ax.grid(alpha=0.3)
